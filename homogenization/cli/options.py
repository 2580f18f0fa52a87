"""Options shared by the commands of ``homogenization.cli``: the parser, the cell and the backend.

- ``command_parser(module, description)``: the parser of a command, named as the user typed
  it, with the flags every command shares and its defaults shown (``warp_hcell.core.cli``);
- ``add_backend_argument(parser)``: --backend, one of the registry's names;
- ``add_alpha0_argument(parser)``: --alpha0 [deg], the opening angle of builder specs;
- ``add_cell_arguments(parser, cell_help, threads_help)``: --mesostructure (a file or a
  builder spec), --threads and --model (the backend-specific options).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from homogenization.backends import BACKENDS
from warp_hcell.core.cli import alpha0_deg, command_parser, positive_int  # noqa: F401 (command_parser: the commands import it from here)
from warp_hcell.core.parameters import CellDefaults
from warp_hcell.mesostructures.builders import MESOSTRUCTURE_HELP, mesostructure_arg


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """--backend, one cell model of ``homogenization.backends.BACKENDS`` (default analytical)."""
    parser.add_argument("--backend", choices=tuple(BACKENDS), default="analytical", help="cell model")


def add_alpha0_argument(parser: argparse.ArgumentParser) -> None:
    """--alpha0 [deg] in [30, 90) (default ``CellDefaults.alpha0_deg``)."""
    parser.add_argument("--alpha0", type=alpha0_deg, default=CellDefaults.alpha0_deg,
                        help="initial opening angle [deg], in [30, 90)")


def add_cell_arguments(parser: argparse.ArgumentParser, cell_help: str, threads_help: str) -> None:
    """--mesostructure (``cell_help`` then the spec grammar), --threads and --model."""
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None, help=f"{cell_help} {MESOSTRUCTURE_HELP}")
    parser.add_argument("--threads", type=positive_int, default=None, help=threads_help)
    parser.add_argument("--model", type=Path, default=None, help="ANN checkpoint (ann only; None: the installed model)")
