"""python -m homogenization.cell ... (``hmodel cell``)

The command is ``homogenization.cli.cell``; this module is its ``python -m`` entry point.
"""

import sys

from homogenization.cli.cell import main
from warp_hcell.core.cli import run_main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(run_main(main))
