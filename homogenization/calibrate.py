"""python -m homogenization.calibrate ... (``hmodel calibrate``)

The command is ``homogenization.cli.calibrate``; this module is its ``python -m`` entry point.
"""

import sys

from homogenization.cli.calibrate import main
from warp_hcell.core.cli import run_main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(run_main(main))
