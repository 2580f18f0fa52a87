"""python -m warp_hcell.clean DB.h5 [--out CLEAN.h5]

The command of the cleaning step (``warp_hcell.database.clean``): marks unconverged and non-finite
samples of a learning database in ``valid`` and prints the counts per reason.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

from warp_hcell.core.cli import command_parser, run_main, say, set_verbosity, UserError
from warp_hcell.database.clean import clean_file, REASONS


def _run(argv: Sequence[str] | None) -> int:
    parser = command_parser(
        "warp_hcell.clean",
        "Mark unconverged and non-finite samples of a learning database in `valid` (mechanism and "
        "perturbed samples are kept) and record the counts per reason as root attrs.",
        device=False)
    parser.add_argument("database", type=Path, help="database file written by warp_hcell.generate")
    parser.add_argument("--out", type=Path, default=None, help="write the cleaned file here; unset: clean in place")
    args = parser.parse_args(argv)
    set_verbosity(args)
    out = args.out or args.database
    if not args.database.is_file():
        raise UserError(f"{args.database}: no such database file")
    if args.out is not None and args.out.exists():
        raise UserError(f"{args.out} exists; remove it or clean in place")
    try:
        summary = clean_file(args.database, out)
    except KeyError as exc:
        raise UserError(f"{args.database}: not a complete learning database ({exc.args[0] if exc.args else exc})") from None
    say(f"{out}: {summary['n_valid']} valid, {summary['n_removed']} removed "
        + ", ".join(f"{reason} {summary[f'removed_{reason}']}" for reason in REASONS))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: clean a database file (see the module docstring); bad input exits 2."""
    return run_main(_run, argv)


if __name__ == "__main__":
    sys.exit(main())
