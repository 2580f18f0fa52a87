"""python -m homogenization.biaxial --backend analytical --alpha0 55 --p0 5.85e6 --eps-max 0.2 --increment 1e-5 --orientations 360 [--drained] [--overwrite] --out DIR

Biaxial test of the H-model: isotropic compression to p0 (strain increments of
--iso-increment, the last one shortened so that p lands on p0), then constant-volume
shear (d_eps11 = +increment, d_eps22 = -increment) or, with --drained, shear at
sigma22 = p0 (stress control), to eps1 = --eps-max counted from the end of stage 1.

--backend takes one name or a comma list (e.g. ``analytical,dem``): every backend runs
the same programme. One backend writes DIR/run.h5 and DIR/curve.csv; several write
DIR/<backend>/run.h5 and DIR/<backend>/curve.csv. Either way DIR/cambridge.png overlays
all backends in the 2x2 figure (q-eps1, q-p, p-eps1 or eps_v-eps1, q/p-eps1).
Backend-specific options go to their backend only: --mesostructure and --threads to dem,
--model to ann, --device to dem and ann. --mesostructure takes a file or a builder spec
(``warp_hcell.builders``, e.g. ``hcell-fines:ratio=0.76``), built at --alpha0 unless the
spec gives its own alpha0.

Sign convention: compression and contraction positive; stresses in N/m (2D). Bad input
(unknown backend, alpha0 outside [30, 90) deg, p0 <= 0, unwritable --out, existing output
without --overwrite) is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

from homogenization import driver, io, loading, plotting
from homogenization.backends import BACKENDS, backend_class, make_cell_model
from warp_hcell.builders import MESOSTRUCTURE_HELP, mesostructure_arg
from warp_hcell.cli import (
    UserError,
    alpha0_deg,
    check_output_path,
    common_parser,
    finite_float,
    positive_float,
    positive_int,
    run_main,
)
from warp_hcell.parameters import CellDefaults, ContactLaw, LoadingDefaults

FIGURE_FILE = "cambridge.png"
BACKEND_ONLY_OPTIONS = {"mesostructure": ("dem",), "threads": ("dem",), "model": ("ann",)}
"""Backend-specific flags (argparse dest) -> the backends that take them."""
DEVICE_BACKENDS = ("dem", "ann")
"""Backends that take --device; the analytical cell runs on the cpu."""


def backend_list(text: str) -> tuple[str, ...]:
    """argparse type: comma list of registered backend names (duplicates dropped, order kept)."""
    names = tuple(dict.fromkeys(name.strip() for name in text.split(",")))
    for name in names:
        if name not in BACKENDS:
            raise argparse.ArgumentTypeError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
    return names


def fabric_anisotropy(text: str) -> float:
    """argparse type: fabric anisotropy a_f in [0, 1)."""
    value = finite_float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"{text} is outside [0, 1)")
    return value


def build_parser() -> argparse.ArgumentParser:
    """Parser of the biaxial command (defaults read from warp_hcell.parameters)."""
    cell, load = CellDefaults(), LoadingDefaults()
    parser = argparse.ArgumentParser(
        prog="python -m homogenization.biaxial",
        description="Isotropic compression to p0, then constant-volume (or drained) biaxial shear of the H-model.",
        parents=[common_parser()],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--backend", type=backend_list, default="analytical",
                        help=f"cell model, or a comma list to overlay several; choices: {', '.join(BACKENDS)}")
    parser.add_argument("--alpha0", type=alpha0_deg, default=cell.alpha0_deg, help="initial opening angle [deg], in [30, 90)")
    parser.add_argument("--p0", type=positive_float, default=cell.p0, help="confining pressure of stage 1 [N/m], > 0")
    parser.add_argument("--eps-max", type=positive_float, default=load.eps_max,
                        help="axial strain at the end of the shear stage, counted from its start [-]")
    parser.add_argument("--increment", type=positive_float, default=load.increment, help="axial strain increment of the shear stage [-]")
    parser.add_argument("--iso-increment", type=positive_float, default=load.iso_increment,
                        help="strain increment per component of the isotropic stage [-]")
    parser.add_argument("--orientations", type=positive_int, default=cell.n_orientations, help="number N of cell orientations")
    parser.add_argument("--fabric-anisotropy", type=fabric_anisotropy, default=0.0,
                        help="a_f of the orientation weights w = (1 + a_f cos 2(theta - b_f)) / pi; 0 = isotropic fabric")
    parser.add_argument("--fabric-direction", type=finite_float, default=0.0, help="preferred fabric direction b_f [deg]")
    parser.add_argument("--drained", action="store_true", help="hold sigma22 = p0 during shear instead of constant volume")
    parser.add_argument("--snapshot-interval", type=positive_int, default=None,
                        help="also store per-cell observables every this many increments (None: at stage ends only)")
    parser.add_argument("--deviator", choices=plotting.DEVIATORS, default=plotting.DEVIATORS[0],
                        help="figure deviator: q = s11 - s22 or t = q/2")
    parser.add_argument("--fourth-panel", choices=plotting.FOURTH_PANELS, default=plotting.FOURTH_PANELS[0],
                        help="fourth panel of the figure: stress ratio or second-order work W2")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None,
                        help=f"dem only; None: the H-cell. {MESOSTRUCTURE_HELP}")
    parser.add_argument("--threads", type=positive_int, default=None, help="CPU threads of the DEM (dem only; None: the backend's own default)")
    parser.add_argument("--model", type=Path, default=None, help="ANN checkpoint (ann only; None: the installed model)")
    return parser


def backend_options(args: argparse.Namespace, name: str) -> dict[str, Any]:
    """Keyword options for backend ``name``: only the flags it takes and the user set."""
    options: dict[str, Any] = {}
    if name in DEVICE_BACKENDS:
        options["device"] = args.device
    for dest, takers in BACKEND_ONLY_OPTIONS.items():
        value = getattr(args, dest)
        if value is not None and name in takers:
            options[dest] = value
    if "mesostructure" in options:
        options["mesostructure"] = options["mesostructure"].build(args.alpha0)
    return options


def check_options(args: argparse.Namespace) -> None:
    """One-line UserError for flags that no chosen backend takes; fail early on unbuilt backends."""
    for dest, takers in BACKEND_ONLY_OPTIONS.items():
        if getattr(args, dest) is not None and not set(takers) & set(args.backend):
            flag = "--" + dest.replace("_", "-")
            raise UserError(f"{flag} applies to --backend {' or '.join(takers)} only")
    if args.device != "cpu" and not set(DEVICE_BACKENDS) & set(args.backend):
        raise UserError(f"--device applies to --backend {' or '.join(DEVICE_BACKENDS)} only (analytical runs on the cpu)")
    for name in args.backend:
        backend_class(name)  # ValueError (one line) if the backend is not built in this version


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    out: Path = args.out
    check_output_path(out, overwrite=args.overwrite)
    check_options(args)
    programme = loading.biaxial(args.p0, args.eps_max, args.increment, iso_increment=args.iso_increment,
                                drained=args.drained)
    law = ContactLaw()
    radius = CellDefaults.radius

    # build every backend first, so that a missing model file fails before any run
    options = {name: backend_options(args, name) for name in args.backend}
    models = {name: make_cell_model(name, contact_law=law, radius=radius, **options[name]) for name in args.backend}
    records: dict[str, driver.Record] = {}
    for name, model in models.items():
        start = time.perf_counter()
        try:
            record = driver.run(model, programme, alpha0_deg=args.alpha0, n_orientations=args.orientations,
                                fabric_anisotropy=args.fabric_anisotropy, fabric_direction_deg=args.fabric_direction,
                                snapshot_interval=args.snapshot_interval or 0)
        except driver.ControlError as exc:
            raise UserError(f"{name}: {exc}") from None
        elapsed = time.perf_counter() - start
        parameters = {
            "backend": name,
            "backend_options": {k: str(v) if isinstance(v, Path) else v for k, v in options[name].items()
                                if k != "mesostructure"},
            "contact_law": asdict(law),
            "radius": radius,
            "alpha0_deg": args.alpha0,
            "p0": args.p0,
            "eps_max": args.eps_max,
            "increment": args.increment,
            "iso_increment": args.iso_increment,
            "n_orientations": args.orientations,
            "fabric_anisotropy": args.fabric_anisotropy,
            "fabric_direction_deg": args.fabric_direction,
            "drained": args.drained,
            "stress_rtol": LoadingDefaults.stress_rtol,
            "mesostructure_file": str(args.mesostructure) if name == "dem" and args.mesostructure else None,
        }
        folder = out if len(args.backend) == 1 else out / name
        try:
            run_path, curve_path = io.write_run(folder, record, parameters=parameters, seed=args.seed)
        except OSError as exc:
            raise UserError(f"cannot write to {folder}: {exc.strerror or exc}") from None
        records[name] = record
        unconverged = record.diagnostics.get("n_unconverged")
        note = f", {int(unconverged.sum())} unconverged cell-increments" if unconverged is not None and unconverged.sum() else ""
        print(f"{name}: {record.n_increments} increments in {elapsed:.1f} s{note} -> {run_path}, {curve_path}")

    kind = "drained" if args.drained else "constant-volume"
    title = f"{kind} biaxial test, alpha0 = {args.alpha0:g} deg, p0 = {args.p0:g} N/m, N = {args.orientations}"
    fig = plotting.make_figure(records, drained=args.drained, fourth=args.fourth_panel, deviator=args.deviator,
                               title=title)
    figure = plotting.save_figure(fig, out / FIGURE_FILE)
    print(f"figure -> {figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
