"""python -m homogenization.cell --backend analytical --alpha0 55 --path PATH.csv --out OUT.csv

Element test of one cell: from its touching, force-free initial state, the cell is driven along
the local strain increments of PATH.csv and its state after every increment is written to OUT.csv.

PATH.csv: header ``d_eps_n,d_eps_t`` then one row per increment [-], compression positive
(l1 <- l1 (1 - d_eps_n), l2 <- l2 (1 - d_eps_t)). A 3D cell (e.g. ``--mesostructure
hcell3d:alpha0=55``) takes ``d_eps_n,d_eps_t1,d_eps_t2`` along its own axes (the axisymmetric
kinematics of ``hcell3d-axisym`` play no part here).

OUT.csv: header ``l1,l2,alpha_deg,d1,d2,N1,N2,T1,S_nn,S_tt`` (with ``--positions`` followed by
the grain centres ``x_n1,x_t1,...`` [m], local frame, cell centre at the origin), one row per
increment: lengths [m], angle [deg], contact forces [N] (compression positive, T1 > 0 resists
opening), Love-Weber moments [N m], compression positive. A 3D cell: ``COLUMNS_3D`` (l1, l2, l3,
the observables of planes A and B with suffix ``_a`` / ``_b`` where reported, S_nn, S_t1t1,
S_t2t2). A cell that is not an H-cell writes only the columns its backend reports among
``observables()``.

The cell is the H-cell of --alpha0 and --radius (``hcell3d`` for a three-column path) or
``--mesostructure`` (a file or a builder spec of ``warp_hcell.mesostructures.builders``); the
analytical backend models the plain H-cells only, the ANN its model's mesostructure.

Bad input (missing or malformed PATH.csv, a path of the wrong dimension, alpha0 outside
[30, 90) deg, a mesostructure the backend does not model, unwritable or busy --out, a missing
CUDA device, and for the ann backend a row with ``|d_eps|`` above its database's largest probe)
is one line on stderr and exit code 2; an existing OUT.csv is kept unless --overwrite.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from homogenization.cli.options import add_alpha0_argument, add_backend_argument, add_uncertified_argument, command_parser, refuse_uncertified
from homogenization.cli.run_files import DEVICE_BACKENDS, warn_unused_alpha0
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.builders import mesostructure_arg, MESOSTRUCTURE_HELP
from warp_hcell.core.cli import (
    UserError,
    add_contact_law_arguments,
    contact_law_from_args,
    quiet_warp,
    run_main,
    say,
    set_verbosity,
    writing_to,
)
from warp_hcell.core.files import atomic_write, check_output_path, output_lock
from warp_hcell.mesostructures.hcell import plain_h_cell
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES, Mesostructure
from warp_hcell.core.parameters import DatabaseSettings

PATH_HEADERS = {dim: tuple(f"d_eps_{axis}" for axis in AXIS_NAMES[dim]) for dim in (2, 3)}
"""Columns of the strain-path file by the cell's dimension: d_eps_n,d_eps_t (2), d_eps_n,d_eps_t1,d_eps_t2 (3)."""
COLUMNS = ("l1", "l2", "alpha_deg", "d1", "d2", "N1", "N2", "T1", "S_nn", "S_tt")
"""Columns of the output file of a planar cell, before the optional grain positions."""
COLUMNS_3D = ("l1", "l2", "l3",
              *(f"{name}_{plane}" for plane in "ab" for name in ("alpha_deg", "d1", "d2", "N1", "N2", "T1")),
              "S_nn", "S_t1t1", "S_t2t2")
"""Columns of the output file of a 3D cell, before the optional grain positions."""
CELL_KINDS = {2: "planar", 3: "3D"}
"""How a message names a cell of each dimension."""
DEFAULT_3D_CELL = "hcell3d"
"""Builder spec of the cell of a three-column path without --mesostructure (``hcell.plain_h_cell(3)``, built
at --alpha0, --radius), as the help names it."""
DEM_ONLY_BACKEND = "dem"
"""The backend whose Warp start-up banner is silenced."""
ANN_MAX_INCREMENT = DatabaseSettings.probe_max
"""Largest ``|d_eps|`` [-] of one path row the ann backend accepts: the largest strain probe of
its learning database (beyond it the network extrapolates)."""


def build_parser() -> argparse.ArgumentParser:
    """Parser of the element-test command (defaults read from warp_hcell.core.parameters)."""
    parser = command_parser("homogenization.cell", "Drive one cell along a local strain path and write its state "
                                                   "after every increment.")
    add_backend_argument(parser)
    add_alpha0_argument(parser)
    parser.add_argument("--path", type=Path, required=True,
                        help="CSV of local strain increments, header d_eps_n,d_eps_t (a 3D cell: d_eps_n,d_eps_t1,"
                             "d_eps_t2), compression positive")
    parser.add_argument("--out", type=Path, required=True, help="output CSV, one row per increment")
    add_contact_law_arguments(parser)
    parser.add_argument("--positions", action="store_true",
                        help="also write the grain centres x_n{i}, x_t{i} [m] (3D: x_n{i}, x_t1{i}, x_t2{i})")
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None,
                        help=f"the cell (analytical: the plain H-cells only; ann: the model's mesostructure); "
                             f"default: the H-cell of --alpha0 and --radius ({DEFAULT_3D_CELL} for a path of three "
                             f"columns). {MESOSTRUCTURE_HELP}")
    add_uncertified_argument(parser)
    return parser


def read_path(path: Path) -> np.ndarray:
    """Read a strain-path CSV; UserError (one line) for anything malformed.

    Args:
        path: file with the header ``d_eps_n,d_eps_t`` (a 3D cell: ``d_eps_n,d_eps_t1,d_eps_t2``,
            ``PATH_HEADERS``) and one row per increment.

    Returns:
        Local strain increments (d_eps_n, d_eps_t) [-], shape (n_increments, 2), or (d_eps_n,
        d_eps_t1, d_eps_t2), shape (n_increments, 3); compression positive, each finite and in (-1, 1).
    """
    if not path.is_file():
        raise UserError(f"path file {path} does not exist")
    try:
        lines = path.read_text(encoding="utf-8-sig").rstrip().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read path file {path}: {exc}") from None
    header = tuple(name.strip() for name in lines[0].split(",")) if lines else ()
    if header not in PATH_HEADERS.values():
        raise UserError(f"{path}: header must be '{','.join(PATH_HEADERS[2])}' (a {CELL_KINDS[2]} cell) or "
                        f"'{','.join(PATH_HEADERS[3])}' (a {CELL_KINDS[3]} cell), got {lines[0] if lines else ''!r}")
    count = {2: "two", 3: "three"}[len(header)]
    if len(lines) == 1:
        raise UserError(f"{path}: no increments after the header")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        try:
            values = [float(field) for field in fields]
        except ValueError:
            values = []
        if len(values) != len(header):
            raise UserError(f"{path} line {number}: expected {count} numbers {','.join(header)}, got {line!r}")
        if not all(math.isfinite(value) and abs(value) < 1.0 for value in values):
            raise UserError(f"{path} line {number}: increments must be finite and in (-1, 1), got {line!r}")
        rows.append(values)
    return np.array(rows, dtype=np.float64)


def _check_out(out: Path, *, overwrite: bool) -> None:
    """check_output_path, plus: --out names a file and its nearest existing parent is a folder."""
    if out.is_dir():
        raise UserError(f"--out {out} is a folder; give a file name")
    check_output_path(out, overwrite=overwrite)


def _backend_options(args: argparse.Namespace) -> dict:
    """Keyword options of the chosen backend: the device goes to the DEM and the ANN."""
    if args.backend in DEVICE_BACKENDS:
        return {"device": args.device}
    takers = " or ".join(DEVICE_BACKENDS)
    if args.device != "cpu":
        raise UserError(f"--device applies to --backend {takers} only ({args.backend} runs on the cpu)")
    return {}


def check_path_for_backend(path: Path, d_eps: np.ndarray, backend: str) -> None:
    """UserError (one line) for path rows the backend cannot do: for the ann, a row with
    ``|d_eps| = sqrt(d_eps_n^2 + d_eps_t^2)`` (3D: of the three components) above ``ANN_MAX_INCREMENT``."""
    if backend != "ann":
        return
    size = np.linalg.norm(d_eps, axis=1)
    too_large = np.flatnonzero(size > ANN_MAX_INCREMENT)
    if too_large.size:
        row = int(too_large[0])
        raise UserError(f"{path} line {row + 2}: |d_eps| = {size[row]:.3g} exceeds {ANN_MAX_INCREMENT:g}, the largest "
                        f"probe the ann was trained on ({too_large.size} such rows); split them into smaller "
                        f"increments or use --backend analytical or dem")


def run_path(model, mesostructure: Mesostructure, d_eps: np.ndarray, *,
             positions: bool) -> tuple[list[str], np.ndarray, dict[str, float]]:
    """Drive one cell of ``model`` along ``d_eps`` from its initial state.

    Args:
        model: a ``warp_hcell.core.contract.CellModel``.
        mesostructure: the cell it starts from.
        d_eps: local strain increments (d_eps_n, d_eps_t) [-], shape (n_increments, 2), or of a 3D
            cell (d_eps_n, d_eps_t1, d_eps_t2), shape (n_increments, 3); compression positive.
        positions: also return the grain centres x_n{i}, x_t{i} [m] (3D: x_n{i}, x_t1{i}, x_t2{i}).

    Returns:
        (columns, table, counts): the names of the observables written, their values after every
        increment, shape (n_increments, n_columns), and the backend's counts (its ``n_*`` diagnostics,
        e.g. the closed form's ``n_alpha_limit``) summed over the increments.
    """
    state = model.init_state(mesostructure, 1)
    rows = []
    counts: dict[str, float] = {}
    columns: list[str] | None = None
    wanted = {2: COLUMNS, 3: COLUMNS_3D}[mesostructure.dim]
    for increment in d_eps:
        state, response = model.step(state, increment[None, :])
        for name, value in response.diagnostics.items():
            if name.startswith("n_"):
                counts[name] = counts.get(name, 0.0) + float(value)
        observed = model.observables(state)
        if columns is None:
            columns = [name for name in wanted if name in observed]
            if positions:
                labels = sorted({int(name[3:]) for name in observed if name.startswith("x_n") and name[3:].isdigit()})
                columns += [f"x_{axis}{label}" for label in labels for axis in AXIS_NAMES[mesostructure.dim]]
        rows.append([float(observed[name][0]) for name in columns])
    return columns, np.array(rows, dtype=np.float64), counts


def path_cell(args: argparse.Namespace, dim: int) -> Mesostructure:
    """The cell of the element test: --mesostructure, else the H-cell of the path's dimension ``dim``
    (``hcell.plain_h_cell``) at --alpha0 and --radius; UserError (one line) where the
    path's columns do not match the cell's dimension."""
    if args.mesostructure is None:
        return plain_h_cell(dim, args.alpha0, args.radius)
    spec = args.mesostructure
    meso = spec.build(args.alpha0, args.radius)
    if meso.dim != dim:
        raise UserError(f"{args.path}: a path of {len(PATH_HEADERS[dim])} columns ({','.join(PATH_HEADERS[dim])}) "
                        f"but --mesostructure {spec.text} is a {CELL_KINDS[meso.dim]} cell, whose "
                        f"path has the header {','.join(PATH_HEADERS[meso.dim])}")
    return meso


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    _check_out(args.out, overwrite=args.overwrite)
    d_eps = read_path(args.path)
    meso = path_cell(args, d_eps.shape[1])
    warn_unused_alpha0(build_parser(), sys.argv[1:] if argv is None else argv, args.mesostructure)
    check_path_for_backend(args.path, d_eps, args.backend)
    if args.backend in (DEM_ONLY_BACKEND, "ann") and not args.verbose:  # the ANN's hybrid may hand cells to the DEM
        quiet_warp(args.device)
    law = contact_law_from_args(args)
    model = make_cell_model(args.backend, contact_law=law, radius=args.radius, dim=meso.dim, **_backend_options(args))
    refuse_uncertified(model, args)
    with output_lock(args.out):
        columns, table, counts = run_path(model, meso, d_eps, positions=args.positions)
        with writing_to(args.out), atomic_write(args.out) as tmp:
            np.savetxt(tmp, table, fmt="%.17g", delimiter=",", header=",".join(columns), comments="")
    fired = ", ".join(f"{name} {value:g}" for name, value in counts.items() if value)
    say(f"{args.backend}: {len(table)} increments -> {args.out}" + (f" (counts over the increments: {fired})"
                                                                    if fired else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
