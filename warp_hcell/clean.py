"""python -m warp_hcell.clean DB.h5 [--out CLEAN.h5]

The command is ``warp_hcell.database.clean``; this module is its ``python -m`` entry point.
"""

import sys

from warp_hcell.database.clean import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
