"""python -m warp_hcell.generate [--mesostructure FILE_OR_SPEC] --samples 300000 --seed 0 --out runs/db.h5

The command is ``warp_hcell.database.generate``; this module is its ``python -m`` entry point.
"""

import sys

from warp_hcell.database.generate import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
