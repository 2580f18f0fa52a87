"""hmodel biaxial --backend analytical --alpha0 55 --p0 5.85e6 --eps-max 0.2 --increment 1e-5 --orientations 360 [--drained] [--overwrite] --out DIR

(also ``python -m homogenization.biaxial``.) Biaxial test of the H-model: isotropic
compression to p0 (strain increments of --iso-increment, by default half the shear
increment, the last one shortened so that p lands on p0), then constant-volume shear
(d_eps11 = +increment, d_eps22 = -increment) or, with --drained, shear at sigma22 = p0
(stress control), to eps1 = --eps-max counted from the end of stage 1. ``--programme FILE``
runs any loading programme instead (JSON or TOML, docs/programmes.md).

--backend takes one name or a comma list (e.g. ``analytical,dem``): every backend runs
the same programme. One backend writes DIR/run.h5 and DIR/curve.csv; several write
DIR/<backend>/run.h5 and DIR/<backend>/curve.csv. Either way DIR/cambridge.png overlays
all backends in the 2x2 figure (q-eps1, q-p, p-eps1 or eps_v-eps1, q/p-eps1).
Every backend's cells start from one mesostructure: the H-cell of --alpha0 and --radius
(``warp_hcell.mesostructures.hcell.h_cell``), or --mesostructure, a file or a builder spec
(``warp_hcell.mesostructures.builders``, e.g. ``hcell-fines:ratio=0.76``) built at --alpha0 unless the spec
gives its own alpha0. A backend that does not model it (the analytical backend models the
plain H-cell only; an ANN model the mesostructure it was trained on) stops the command before
any run. Backend-specific options go to their backend only: --threads to dem and ann, --model
to ann, --device to dem and ann.

The output folder DIR is written as a unit: everything goes to a hidden sibling folder
that replaces DIR only when the run has finished (--overwrite), so an interrupted run
leaves the previous output as it was. A second run on the same DIR exits at once.

Sign convention: compression and contraction positive; stresses in N/m (2D). Bad input
(unknown backend, alpha0 outside [30, 90) deg, a mesostructure a backend does not model,
p0 <= 0, an increment larger than
--eps-max, a malformed programme, a CUDA device the machine lacks, unwritable --out,
existing output without --overwrite, DIR busy) is one line on stderr and exit code 2.
Increments coarser than the learning database's largest probe (1e-3) are run with a
warning: the macro kinematics errs by ~1 % of p0 there and the ANN extrapolates.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

from homogenization import driver, figures, io, loading
from homogenization.cli import plot
from homogenization.cli.options import add_cell_arguments, add_uncertified_argument, certificate_note, refuse_uncertified
from homogenization.backends import backend_class, BACKENDS, make_cell_model
from warp_hcell.core.cli import (
    Parser,
    UserError,
    add_contact_law_arguments,
    alpha0_deg,
    command_prog,
    common_parser,
    contact_law_from_args,
    finite_float,
    fraction,
    positive_float,
    positive_int,
    quiet_warp,
    run_main,
    say,
    set_verbosity,
)
from warp_hcell.core.files import check_output_path, output_folder, output_lock
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import CellDefaults, DatabaseSettings, LoadingDefaults
from warp_hcell.core.provenance import command_line, file_sha256

FIGURE_FILE = "cambridge.png"
BACKEND_ONLY_OPTIONS = {"threads": ("dem", "ann"), "model": ("ann",)}
"""Backend-specific flags (argparse dest) -> the backends that take them."""
DEVICE_BACKENDS = ("dem", "ann")
"""Backends that take --device; the analytical cell runs on the cpu."""
ISO_TO_SHEAR_INCREMENT = LoadingDefaults.iso_increment / LoadingDefaults.increment
"""Default --iso-increment as a fraction of --increment (5e-6 / 1e-5 = 0.5)."""
COARSE_INCREMENT = DatabaseSettings.probe_max
"""Strain increment [-] above which a run is warned about: the learning database's largest
probe (the ANN extrapolates beyond it) and where the macro kinematics of every backend errs
by ~1 % of p0 (docs/dem_homogenization.md)."""
PROGRAMME_FLAGS = {"p0": "--p0", "eps_max": "--eps-max", "increment": "--increment",
                   "iso_increment": "--iso-increment", "drained": "--drained"}
"""Flags that define the built-in programme, so conflict with --programme (argparse dest -> flag)."""


def backend_list(text: str) -> tuple[str, ...]:
    """argparse type: comma list of registered backend names (duplicates dropped, order kept)."""
    names = tuple(dict.fromkeys(name.strip() for name in text.split(",")))
    for name in names:
        if name not in BACKENDS:
            raise argparse.ArgumentTypeError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
    return names


def build_parser() -> argparse.ArgumentParser:
    """Parser of the biaxial command (defaults read from warp_hcell.core.parameters)."""
    cell, load = CellDefaults(), LoadingDefaults()
    parser = Parser(
        prog=command_prog("homogenization.biaxial"),
        description="Isotropic compression to p0, then constant-volume (or drained) biaxial shear of the H-model, "
                    "or any loading programme file.",
        parents=[common_parser()],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--backend", type=backend_list, default="analytical",
                        help=f"cell model, or a comma list to overlay several; choices: {', '.join(BACKENDS)}")
    parser.add_argument("--alpha0", type=alpha0_deg, default=cell.alpha0_deg, help="initial opening angle [deg], in [30, 90)")
    loading_group = parser.add_argument_group("built-in programme (not with --programme)")
    loading_group.add_argument("--p0", type=positive_float, default=cell.p0, help="confining pressure of stage 1 [N/m], > 0")
    loading_group.add_argument("--eps-max", type=positive_float, default=load.eps_max,
                               help="axial strain at the end of the shear stage, counted from its start [-]")
    loading_group.add_argument("--increment", type=positive_float, default=load.increment,
                               help="axial strain increment of the shear stage [-], <= --eps-max")
    loading_group.add_argument("--iso-increment", type=positive_float, default=argparse.SUPPRESS,
                               help=f"strain increment per component of the isotropic stage [-] "
                                    f"(default: {ISO_TO_SHEAR_INCREMENT:g} x --increment)")
    loading_group.add_argument("--drained", action="store_true", help="hold sigma22 = p0 during shear instead of constant volume")
    parser.add_argument("--programme", type=Path, default=None,
                        help="JSON or TOML loading programme (format of homogenization.loading.to_dict; "
                             "docs/programmes.md, examples in homogenization/data/programmes/)")
    parser.add_argument("--orientations", type=positive_int, default=cell.n_orientations, help="number N of cell orientations")
    parser.add_argument("--fabric-anisotropy", type=fraction, default=0.0,
                        help="a_f of the orientation weights w = (1 + a_f cos 2(theta - b_f)) / pi; 0 = isotropic fabric")
    parser.add_argument("--fabric-direction", type=finite_float, default=0.0, help="preferred fabric direction b_f [deg]")
    add_contact_law_arguments(parser)
    parser.add_argument("--snapshot-interval", type=positive_int, default=None,
                        help="also store per-cell observables every this many increments (None: at stage ends only)")
    plot.add_figure_arguments(parser.add_argument_group("figure (cambridge.png)"))
    parser.add_argument("--out", type=Path, required=True, help="output folder (replaced as a unit)")
    add_cell_arguments(parser, "the cell of every backend (analytical: the plain H-cell only; ann: the model's "
                               "mesostructure); None: the H-cell of --alpha0 and --radius.",
                       "CPU threads of the DEM or of torch inference (dem and ann; None: the backend's own default)")
    add_uncertified_argument(parser)
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
    return options


def run_mesostructure(args: argparse.Namespace) -> Mesostructure:
    """The cell of the run: --mesostructure built at --alpha0, else the H-cell of --alpha0 and --radius.

    Raises:
        warp_hcell.mesostructures.mesostructure.MesostructureError: a file or spec that does not build (one line).
    """
    if args.mesostructure is not None:
        return args.mesostructure.build(args.alpha0)
    return h_cell(args.alpha0, args.radius)


def check_models_take(models: dict[str, Any], meso: Mesostructure) -> None:
    """UserError (one line) unless every backend builds a cell of ``meso`` (checked before any run)."""
    for name, model in models.items():
        try:
            model.init_state(meso, 1)
        except ValueError as exc:
            raise UserError(f"{name}: {exc}") from None


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
    if args.device != "cpu" and "ann" in args.backend:
        import torch  # noqa: PLC0415 (only when the ANN is asked for a GPU)

        if not torch.cuda.is_available():
            raise UserError(f"--device {args.device}: the installed torch has no CUDA support; use --device cpu for the ann")


def explicit_flags(argv: Sequence[str], dests: Sequence[str]) -> set[str]:
    """The argparse dests among ``dests`` that ``argv`` sets explicitly (not by default)."""
    unset = object()  # not a string, so argparse does not run it through type=
    probe = build_parser()
    probe.set_defaults(**{dest: unset for dest in dests})
    parsed = vars(probe.parse_args(argv))
    return {dest for dest in dests if parsed.get(dest, unset) is not unset}


def build_programme(args: argparse.Namespace, argv: Sequence[str]) -> tuple[loading.Programme, dict[str, Any]]:
    """The programme of the run: the ``--programme`` file, else the built-in biaxial test.

    Returns:
        (programme, the resolved built-in settings p0, eps_max, increment, iso_increment,
        or the programme file name).

    Raises:
        UserError: built-in programme flags given with --programme, or an increment larger
            than --eps-max (it would be silently cut to one increment).
    """
    if args.programme is not None:
        explicit = explicit_flags(argv, tuple(PROGRAMME_FLAGS))
        given = [flag for dest, flag in PROGRAMME_FLAGS.items() if dest in explicit]
        if given:
            raise UserError(f"{', '.join(given)} do not apply with --programme (the file holds the whole programme)")
        return loading.read_programme(args.programme), {"programme_file": str(args.programme)}
    p0, eps_max, increment = args.p0, args.eps_max, args.increment
    if increment > eps_max:
        raise UserError(f"--increment {increment:g} is larger than --eps-max {eps_max:g}: the shear stage would be "
                        f"one increment of {eps_max:g}; use an increment <= {COARSE_INCREMENT:g}")
    iso_increment = getattr(args, "iso_increment", ISO_TO_SHEAR_INCREMENT * increment)
    if iso_increment >= loading.ISO_MAX_STRAIN:
        raise UserError(f"--iso-increment {iso_increment:g} must be < {loading.ISO_MAX_STRAIN:g}, "
                        f"the largest isotropic strain allowed")
    settings = {"p0": p0, "eps_max": eps_max, "increment": increment, "iso_increment": iso_increment}
    return loading.biaxial(p0, eps_max, increment, iso_increment=iso_increment, drained=args.drained), settings


def coarse_steps(programme: loading.Programme) -> list[tuple[str, float]]:
    """(label, largest strain-controlled increment [-]) of the steps coarser than ``COARSE_INCREMENT``."""
    coarse = []
    for step in programme:
        largest = max((abs(t) / step.n_increments for c, t in zip(step.control, step.target) if c == "strain"), default=0.0)
        if largest > COARSE_INCREMENT:
            coarse.append((step.label, largest))
    return coarse


def warn(message: str) -> None:
    """One warning line on stderr."""
    print(f"hmodel biaxial: warning: {message}", file=sys.stderr)


def check_replaceable(out: Path) -> None:
    """UserError unless ``out`` is absent or holds only what this command writes.

    --overwrite replaces the whole folder, so it must not hold anything else (``--out .``
    with --overwrite would otherwise delete the working folder).
    """
    if not out.is_dir():
        if out.exists():
            raise UserError(f"--out {out} is a file; give a folder")
        return
    ours = {io.RUN_FILE, io.CURVE_FILE, FIGURE_FILE, *BACKENDS}
    foreign = sorted(p.name for p in out.iterdir() if p.name not in ours)
    if foreign:
        raise UserError(f"{out} holds files that this command did not write ({', '.join(foreign[:3])}); "
                        f"choose another --out")


def provenance_of(name: str, model: Any, options: dict[str, Any]) -> dict[str, Any]:
    """Backend settings worth recording: DEM settings and threads, ANN model path and sha256."""
    record: dict[str, Any] = {}
    if hasattr(model, "settings"):
        record["dem_settings"] = asdict(model.settings)
    if hasattr(model, "threads"):
        record["dem_threads"] = int(model.threads)
    if name == "ann":
        path = getattr(model, "model_path", None) or options.get("model")
        if path is None:
            from homogenization.backends.ann import default_model_path  # noqa: PLC0415

            path = default_model_path()
        path = Path(path).resolve()
        record["ann_model"] = {"path": str(path), "sha256": file_sha256(path),
                               "certificate_worst": (model.certificate or {}).get("worst"),
                               "certified": model.certificate_problem is None,
                               "certificate_problem": model.certificate_problem}
        if model.ood is not None:
            record["ann_model"]["ood"] = {"checked": int(model.ood_counts[1]), "outside": int(model.ood_counts[0]),
                                          "threshold": model.ood.threshold}
    return record


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    command = command_line() if argv is None else shlex.join(["hmodel", "biaxial", *argv])
    out: Path = args.out
    if "dem" in args.backend and not args.verbose:
        quiet_warp(args.device)
    check_output_path(out, overwrite=args.overwrite)
    check_replaceable(out)
    check_options(args)
    programme, settings = build_programme(args, sys.argv[1:] if argv is None else argv)
    if args.normalise and not any(step.stop_at_p for step in programme):
        raise UserError("--normalise needs p0: the programme has no stop_at_p step")
    for label, largest in coarse_steps(programme):
        warn(f"step {label!r} has strain increments up to {largest:g} > {COARSE_INCREMENT:g}: coarse kinematics "
             f"(~1 % of p0 and more){'; the ANN extrapolates beyond its training probes' if 'ann' in args.backend else ''}")
    law = contact_law_from_args(args)
    if args.verbose:
        say(f"programme: {loading.to_dict(programme)}", f"contact law: {asdict(law)}, radius {args.radius:g} m")

    meso = run_mesostructure(args)
    with output_lock(out):
        # build every backend and a cell of the mesostructure first, so that a missing model
        # file or a mesostructure a backend does not model fails before any run
        options = {name: backend_options(args, name) for name in args.backend}
        models = {name: make_cell_model(name, contact_law=law, radius=args.radius, **options[name])
                  for name in args.backend}
        check_models_take(models, meso)
        for model in models.values():
            refuse_uncertified(model, args)
        runs: dict[str, figures.Run] = {}
        written: list[str] = []  # status lines, printed once the folder is in place
        drained = figures.is_drained({"drained": args.drained or None}, programme)
        with output_folder(out) as work:
            for name, model in models.items():
                start = time.perf_counter()
                try:
                    record = driver.run(model, programme, mesostructure=meso, n_orientations=args.orientations,
                                        fabric_anisotropy=args.fabric_anisotropy,
                                        fabric_direction_deg=args.fabric_direction,
                                        snapshot_interval=args.snapshot_interval or 0)
                except driver.ControlError as exc:
                    raise UserError(f"{name}: {exc}") from None
                elapsed = time.perf_counter() - start
                parameters = {
                    "backend": name,
                    "backend_options": {k: str(v) if isinstance(v, Path) else v for k, v in options[name].items()},
                    **provenance_of(name, model, options[name]),
                    "contact_law": asdict(law),
                    "radius": args.radius,
                    "alpha0_deg": meso.parameters.get("alpha0_deg"),
                    "p0": next((s.stop_at_p for s in programme if s.stop_at_p is not None), None),
                    **settings,
                    "n_orientations": args.orientations,
                    "fabric_anisotropy": args.fabric_anisotropy,
                    "fabric_direction_deg": args.fabric_direction,
                    "drained": drained,
                    "stress_rtol": LoadingDefaults.stress_rtol,
                    "mesostructure": args.mesostructure.text if args.mesostructure is not None else None,
                }
                folder = work if len(args.backend) == 1 else work / name
                final = out if len(args.backend) == 1 else out / name
                try:
                    io.write_run(folder, record, parameters=parameters, seed=args.seed, command=command)
                except OSError as exc:
                    raise UserError(f"cannot write to {out}: {exc.strerror or exc}") from None
                runs[name] = figures.Run(record, parameters)
                unconverged = record.diagnostics.get("n_unconverged")
                note = f", {int(unconverged.sum())} unconverged cell-increments" if unconverged is not None and unconverged.sum() else ""
                note += certificate_note(model)
                if getattr(model, "ood", None) is not None:
                    note += f", out of distribution {int(model.ood_counts[0])} of {int(model.ood_counts[1])} checked cell-increments"
                written.append(f"{name}: {record.n_increments} increments in {elapsed:.1f} s{note} -> "
                               f"{final / io.RUN_FILE}, {final / io.CURVE_FILE}")

            slopes = (figures.critical_state_lines(list(runs.values()), list(runs), warn) if args.csl else None)
            fig = figures.overlay_figure(list(runs.values()), fourth=args.fourth_panel, deviator=args.deviator,
                                          normalise=args.normalise, csl=slopes)
            try:
                figures.save_figure(fig, work / FIGURE_FILE)
            except OSError as exc:
                raise UserError(f"cannot write to {out}: {exc.strerror or exc}") from None
    say(*written, f"figure -> {out / FIGURE_FILE}" + (f" ({plot.csl_summary(slopes)})" if slopes is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
