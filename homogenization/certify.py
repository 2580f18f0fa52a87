"""python -m homogenization.certify ... (``hmodel certify``)

The command is ``homogenization.cli.certify``; this module is its ``python -m`` entry point
(the library is ``homogenization.learning.certificate``).
"""

import sys

from homogenization.cli.certify import main
from warp_hcell.core.cli import run_main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(run_main(main))
