"""hmodel COMMAND [options] (console script), also ``python -m homogenization.hmodel``

The command is ``homogenization.cli.hmodel``; this module is its ``python -m`` entry point.
"""

import sys

from homogenization.cli.hmodel import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
