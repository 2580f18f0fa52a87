"""python -m homogenization.sweep ... (``hmodel sweep``)

The command is ``homogenization.cli.sweep``; this module is its ``python -m`` entry point.
"""

import sys

from homogenization.cli.sweep import main
from warp_hcell.core.cli import run_main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(run_main(main))
