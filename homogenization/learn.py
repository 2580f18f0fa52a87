"""python -m homogenization.learn ... (``hmodel learn``)

The command is ``homogenization.cli.learn``; this module is its ``python -m`` entry point.
"""

import sys

from homogenization.cli.learn import main
from warp_hcell.core.cli import run_main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(run_main(main))
