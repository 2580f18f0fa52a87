"""hmodel triaxial --backend analytical,dem --mesostructure hcell3d:alpha0=55 --p0 2e5 --undrained --eps-max 0.15 --increment 1e-4 --out DIR

(also ``python -m homogenization.triaxial``.) Triaxial tests of the 3D H-model (ten-sphere cells
oriented by ``homogenization.material.orientation``): isotropic compression to p0 (increments of
--iso-increment, default half the shear increment, the last one shortened so that p lands on
p0), then one shear stage (axis 1 axial, --eps-max of axial strain in increments of --increment):

- ``--undrained`` (default): isochoric compression, (1 - d_eps1)(1 - d_eps2)^2 = 1, d_eps2 = d_eps3;
- ``--drained``: compression at sigma2 = sigma3 = p0; ``--extension``: extension at sigma2 = sigma3 = p0;
- ``--constant-p``: compression at p = p0, sigma2 = sigma3;
- ``--true B``: true triaxial at p = p0 and b = (sigma2 - sigma3)/(sigma1 - sigma3) = B;
- ``--cyclic N``: N undrained cycles of axial strain amplitude --eps-max;
- ``--oedometer U``: K0 compression (lateral strains zero) by --eps-max from p0, then unloading
  by U; each backend also writes oedometer.csv (``homogenization.output.oedometer``).

``--void-ratio E`` starts the cells at the alpha0 that the void-ratio map (--e-min, --e-max;
``homogenization.material.density``) gives E, instead of --alpha0.

``--posterior DIR/posterior.json`` (of ``hmodel calibrate``) runs at its posterior mean, with
its alpha0_spread and its interlocking friction where it holds them (analytical backend); ``--posterior-band N`` adds the 95 %
band of N draws (``homogenization.cli.posterior_flags``). ``--programme FILE`` runs any
programme of three-component steps instead (docs/programmes.md).

Outputs as ``hmodel biaxial``: DIR/run.h5 and DIR/curve.csv (header
``stage,eps11,eps22,eps33,sigma11,sigma22,sigma33,p,q,e``, e the current void ratio) per backend, DIR/triaxial.png overlaying
every backend; the folder is replaced as a unit (--overwrite), and an interrupted run resumes as
``hmodel biaxial``'s (--checkpoint-seconds, --restart).

Sign convention: compression and contraction positive; stresses in Pa. Bad input (unknown
backend, an ann model without a passed certificate of its own file unless --uncertified-ok, a
planar mesostructure, p0 <= 0, an increment larger than --eps-max, an --oedometer unloading
outside [0, --eps-max], a programme of planar steps, --void-ratio outside [--e-min, --e-max], negative or with
--alpha0, existing output without --overwrite) is
one line on stderr and exit code 2, before any run.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

from homogenization.element_test import driver, programme as programmes
from homogenization.cli.progress import stage_bars
from homogenization.output import figures, oedometer
from homogenization.backends import BACKENDS
from homogenization.cli import posterior_flags
from homogenization.cli.options import add_alpha0_argument, add_backend_list_argument, add_cell_arguments, add_checkpoint_arguments, add_equilibrium_arguments, add_posterior_arguments, add_programme_arguments, add_uncertified_argument, add_void_ratio_arguments, add_critical_state_argument, command_parser, lebedev_order
from homogenization.cli.run_files import build_models, check_run, checkpoint_folder, refuse_programme_flags, resolve_void_ratio, resumable, run_backends, run_checkpoints, shear_iso_increment, warn_unused_alpha0
from warp_hcell.core.cli import (
    UserError,
    add_contact_law_arguments,
    contact_law_from_args,
    finite_float,
    positive_int,
    run_main,
    say,
    set_verbosity,
    writing_to,
)
from warp_hcell.core.files import output_folder, output_lock
from warp_hcell.core.parameters import LoadingDefaults
from warp_hcell.core.provenance import command_line
from warp_hcell.mesostructures.builders import mesostructure_arg
from warp_hcell.mesostructures.mesostructure import Mesostructure

FIGURE_FILE = "triaxial.png"
DEFAULT_MESOSTRUCTURE = "hcell3d"
"""Builder spec of the cell when --mesostructure is not given (built at --alpha0 and --radius)."""
TESTS = {"undrained": "--undrained", "drained": "--drained", "extension": "--extension",
         "constant_p": "--constant-p", "true": "--true", "cyclic": "--cyclic", "oedometer": "--oedometer"}
"""Shear stage (``programme.TRIAXIAL_TESTS``) -> its flag."""
PROGRAMME_FLAGS = {"p0": "--p0", "eps_max": "--eps-max", "increment": "--increment",
                   "iso_increment": "--iso-increment", **{name: flag for name, flag in TESTS.items()}}
"""Flags of the built-in programme, which conflict with --programme (argparse dest -> flag)."""


def b_ratio(text: str) -> float:
    """argparse type: b in [0, 1]."""
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"b = {value:g} must be in [0, 1]")
    return value


def build_parser() -> argparse.ArgumentParser:
    """Parser of the triaxial command."""
    parser = command_parser("homogenization.triaxial", "Isotropic compression to p0, then a triaxial test of the 3D "
                                                       "H-model (undrained, drained, extension, constant p, true "
                                                       "triaxial, cyclic), or any 3D loading programme file.")
    add_backend_list_argument(parser, ("analytical",), " (ann: the shipped 3D model of the loose cell, or --model; "
                                                       "each backend's cost per cell-increment: docs/ann.md, Speed)")
    add_alpha0_argument(parser)
    add_void_ratio_arguments(parser)
    add_critical_state_argument(parser)
    group = add_programme_arguments(
        parser, stress_unit="Pa", eps_max=0.15, increment=1e-4,
        eps_max_help="axial strain (amplitude of --cyclic) of the shear stage, counted from its start [-]")
    tests = group.add_mutually_exclusive_group()
    tests.add_argument("--undrained", action="store_true", help="isochoric compression (the default test)")
    tests.add_argument("--drained", action="store_true", help="compression at sigma2 = sigma3 = p0")
    tests.add_argument("--extension", action="store_true", help="extension at sigma2 = sigma3 = p0")
    tests.add_argument("--constant-p", action="store_true", help="compression at p = p0, sigma2 = sigma3")
    tests.add_argument("--true", type=b_ratio, default=None, metavar="B",
                       help="true triaxial compression at p = p0 and b = (s2 - s3)/(s1 - s3) = B in [0, 1]")
    tests.add_argument("--cyclic", type=positive_int, default=None, metavar="N",
                       help="N undrained cycles of axial strain amplitude --eps-max")
    tests.add_argument("--oedometer", type=finite_float, default=None, metavar="U",
                       help="oedometric (K0) test, lateral strains held at zero: axial loading by --eps-max from the "
                            "seating stress p0, then unloading by U of axial strain, in [0, --eps-max] (0: none); "
                            "also writes oedometer.csv (sigma_v, sigma_h, K0, eps_v)")
    parser.add_argument("--programme", type=Path, default=None,
                        help="JSON or TOML loading programme of three-component steps (docs/programmes.md)")
    parser.add_argument("--order", type=lebedev_order, default=driver.LEBEDEV_ORDER,
                        help="Lebedev order of the cell axes (53: 487 axes on the hemisphere; docs/triaxial.md, Quadrature)")
    parser.add_argument("--spins", type=positive_int, default=driver.N_SPINS, help="spins of each cell about its axis")
    parser.add_argument("--aligned-spins", action="store_true",
                        help="give every axis the same spins (exact cube symmetry of the rule: sigma22 = sigma33 on "
                             "axisymmetric paths) instead of staggering them (faster convergence; docs/triaxial.md)")
    add_contact_law_arguments(parser)
    parser.add_argument("--out", type=Path, required=True, help="output folder (replaced as a unit)")
    add_cell_arguments(parser, f"the 3D cell of every backend (analytical: the plain ten-sphere cell only); "
                               f"None: {DEFAULT_MESOSTRUCTURE} at --alpha0 and --radius.",
                       "CPU threads of the DEM (None: its own default)")
    add_equilibrium_arguments(parser, "ann only: after the network's step, up to K exact Newton steps on the balance "
                                      "of the free grains with the exact contact law, in cells whose force ratio "
                                      "exceeds the tolerance (a hybrid surrogate, recorded in run.h5 and counted per "
                                      "increment; docs/ann.md)")
    add_uncertified_argument(parser)
    add_posterior_arguments(parser)
    add_checkpoint_arguments(parser)
    return parser


def chosen_test(args: argparse.Namespace) -> str:
    """The shear stage the flags ask for (``programme.TRIAXIAL_TESTS``); undrained by default."""
    if args.true is not None:
        return "true"
    if args.cyclic is not None:
        return "cyclic"
    if args.oedometer is not None:
        return "oedometer"
    return next((name for name in ("drained", "extension", "constant_p") if getattr(args, name)), "undrained")


def build_programme(args: argparse.Namespace, argv: Sequence[str]) -> tuple[programmes.Programme, dict[str, Any]]:
    """The programme of the run (the --programme file or the built-in test) and its settings; UserError
    (one line) for conflicting flags, an increment above --eps-max or a file of planar steps."""
    if args.programme is not None:
        refuse_programme_flags(build_parser(), argv, PROGRAMME_FLAGS)
        programme = programmes.read_programme(args.programme)
        if programmes.dimension(programme) != 3:
            raise UserError(f"{args.programme}: its steps control two components (a biaxial programme); "
                            f"hmodel triaxial takes steps of three (11, 22, 33)")
        return programme, {"programme_file": str(args.programme)}
    iso_increment = shear_iso_increment(args)
    test = chosen_test(args)
    b = args.true if args.true is not None else 0.5
    cycles = args.cyclic or 1
    settings = {"p0": args.p0, "eps_max": args.eps_max, "increment": args.increment, "iso_increment": iso_increment,
                "test": test, **({"b": b} if test == "true" else {}), **({"cycles": cycles} if test == "cyclic" else {})}
    if test == "oedometer":
        if not 0.0 <= args.oedometer <= args.eps_max:
            raise UserError(f"--oedometer {args.oedometer:g}: the unloading strain must be in [0, --eps-max "
                            f"{args.eps_max:g}] (the loading strain)")
        settings["eps_unload"] = args.oedometer
        return programmes.oedometric(args.p0, args.eps_max, args.oedometer, args.increment,
                                  iso_increment=iso_increment), settings
    programme = programmes.triaxial(args.p0, args.eps_max, args.increment, test=test, iso_increment=iso_increment,
                                 b=b, cycles=cycles)
    return programme, settings


def run_mesostructure(args: argparse.Namespace) -> Mesostructure:
    """The 3D cell of the run: --mesostructure (or ``DEFAULT_MESOSTRUCTURE``) built at --alpha0 and --radius; UserError
    (one line) for a planar cell."""
    spec = args.mesostructure if args.mesostructure is not None else mesostructure_arg(
        f"{DEFAULT_MESOSTRUCTURE}:radius={args.radius!r}")
    meso = spec.build(args.alpha0, args.radius)
    if meso.dim != 3:
        raise UserError(f"--mesostructure {spec.text}: a planar cell; hmodel triaxial needs a 3D cell "
                        f"(e.g. hcell3d:alpha0=55 or hcell3d-fines:ratio=0.5)")
    return meso


def check_backends(names: Sequence[str], model: Path | None) -> None:
    """UserError (one line) for a backend without 3D cells, or the ann without ``model`` (--model) where
    no 3D meso-ANN model is installed."""
    for name in names:
        if name == "ann" and model is None:
            from homogenization.ann import default_model_path  # noqa: PLC0415 (torch)

            if not default_model_path(3).is_file():
                raise UserError("--backend ann: no 3D meso-ANN model is shipped; pass --model M.pt, a model trained "
                                "on a 3D database (docs/triaxial.md, 3D meso-ANN)")
        if 3 not in BACKENDS[name]:
            raise UserError(f"--backend {name}: does not model 3D cells")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    command = command_line() if argv is None else shlex.join(["hmodel", "triaxial", *argv])
    out: Path = args.out
    argv_given = sys.argv[1:] if argv is None else argv
    check_backends(args.backend, args.model)
    calibrated = posterior_flags.apply_posterior(args, argv_given, build_parser(), dim=3)
    density_map = resolve_void_ratio(args, argv_given, build_parser(), dim=3)
    critical_state = posterior_flags.critical_state(calibrated, args, 3)
    check_run(args, FIGURE_FILE, posterior_flags.BAND_FILE, oedometer.FILE)
    programme, settings = build_programme(args, argv_given)
    posterior_flags.check_band_test(calibrated, settings, "")
    law = contact_law_from_args(args)
    meso = run_mesostructure(args)
    warn_unused_alpha0(build_parser(), argv_given, args.mesostructure)
    spin_period = meso.spin_period_deg()
    if args.verbose:
        say(f"programme: {programmes.to_dict(programme)}", f"contact law: {law.to_dict()}, radius {args.radius:g} m")
    with output_lock(out):
        models, options = build_models(args, law, meso, dim=3)
        models = posterior_flags.spread_models(calibrated, models, meso, lebedev_order=args.order, n_spins=args.spins,
                                               staggered_spins=not args.aligned_spins)
        renewal = posterior_flags.interlocking_renewal(calibrated, meso, critical_state, args.void_ratio)
        checkpoints = run_checkpoints(args, models, options, law, meso, programme)
        with resumable(out, checkpoints), output_folder(out) as work:
            runs, _, written = run_backends(
                args, models, options, law, meso,
                run=lambda model, checkpoint: driver.run(model, programme, mesostructure=meso, lebedev_order=args.order,
                                             n_spins=args.spins, spin_period_deg=spin_period,
                                             staggered_spins=not args.aligned_spins,
                                             void_ratio=args.void_ratio, density_map=density_map,
                                             critical_state=critical_state, renewal=renewal, progress=stage_bars,
                                             checkpoint=checkpoint),
                parameters=lambda record: {
                    **settings,
                    "lebedev_order": args.order,
                    "n_spins": args.spins,
                    "spin_period_deg": spin_period,
                    "staggered_spins": not args.aligned_spins,
                    "n_orientations": record.weights.size,
                    "stress_rtol": LoadingDefaults.stress_rtol,
                    "mesostructure": args.mesostructure.text if args.mesostructure is not None else DEFAULT_MESOSTRUCTURE,
                    **posterior_flags.run_record(calibrated),
                    "void_ratio": args.void_ratio,
                    "density_map": None if density_map is None else density_map.to_dict(),
                    **({} if critical_state is None else {"critical_state": asdict(critical_state)}),
                    **({} if calibrated is None or calibrated.interlocking is None else
                       {"interlocking": asdict(calibrated.interlocking)}),
                },
                work=work, command=command, checkpoints=checkpoints)
            if settings.get("test") == "oedometer":
                with writing_to(out):
                    for name, record in runs.items():
                        oedometer.write_csv((work / name if len(runs) > 1 else work) / oedometer.FILE, record)
            posterior_flags.compute_band(calibrated, dim=3, drained=settings.get("test") == "drained", p0=args.p0,
                                         eps_max=args.eps_max)
            with writing_to(out):
                band_line = posterior_flags.write_band(calibrated, work)
            title = f"{meso.name}, p0 = {args.p0:g} Pa, {settings.get('test', 'programme')}"
            fig = figures.triaxial_figure(runs, title=title)
            posterior_flags.shade(fig, calibrated, ((1, "q", 1.0), (2, "eps_v", 100.0)))
            with writing_to(out):
                figures.save_figure(fig, work / FIGURE_FILE)
        shutil.rmtree(checkpoint_folder(out), ignore_errors=True)  # the run is in place: its checkpoints are spent
    say(*written, *([band_line.replace(posterior_flags.BAND_FILE, str(out / posterior_flags.BAND_FILE))]
                    if band_line else []),
        f"figure -> {out / FIGURE_FILE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
