"""hmodel biaxial --backend analytical --alpha0 55 --p0 5.85e6 --eps-max 0.2 --increment 1e-5 --orientations 360 [--drained] [--overwrite] --out DIR

(also ``python -m homogenization.biaxial``.) Biaxial test of the H-model: isotropic
compression to p0 (increments of --iso-increment, default half the shear increment, the last
one shortened so that p lands on p0), then constant-volume shear (d_eps11 = +increment,
d_eps22 = -increment) or, with --drained, shear at sigma22 = p0, to eps1 = --eps-max counted
from the end of stage 1. ``--programme FILE`` runs any loading programme instead
(docs/programmes.md). ``--void-ratio E`` starts the cells at the alpha0 that the void-ratio map
(--e-min, --e-max; ``homogenization.material.density``) gives E, instead of --alpha0; curve.csv's
last column ``e`` is the current void ratio.

``--posterior DIR/posterior.json`` (of ``hmodel calibrate``) runs at its posterior mean instead
of --phi, --kn, --kt, --alpha0 and --radius; ``--posterior-band N`` adds the 95 % band of N
posterior draws (DIR/posterior_band.csv; ``homogenization.cli.posterior_flags``).

--backend takes one name or a comma list: every backend runs the same programme. One backend
writes DIR/run.h5 and DIR/curve.csv, several DIR/<backend>/...; DIR/cambridge.png overlays all
backends (q-eps1, q-p, p-eps1 or eps_v-eps1, q/p-eps1). The cells start from the H-cell of
--alpha0 and --radius, or --mesostructure (a file or a builder spec, built at --alpha0 and --radius unless it
gives its own); a backend that does not model it stops the command before any run.
Backend-specific options go to their backend only (--threads, --model, --device).

DIR is written as a unit: a hidden sibling folder replaces it only when the run has finished
(--overwrite); a second run on the same DIR exits at once. A run interrupted (Ctrl-C, kill)
resumes when the same command runs again, from its last checkpoint (--checkpoint-seconds, in
.DIR.resume), with the uninterrupted run's result; --restart discards the checkpoint.

Sign convention: compression and contraction positive; stresses in N/m (2D). Bad input
(unknown backend, alpha0 outside [30, 90) deg, --void-ratio outside [--e-min, --e-max], negative
or with --alpha0, an unmodelled mesostructure, p0 <= 0, an
increment larger than --eps-max, a malformed programme, a missing CUDA device, unwritable
--out, existing output without --overwrite, DIR busy) is one line on stderr and exit code 2.
Increments above the learning database's largest probe (1e-3) run with a warning.
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
from homogenization.output import figures
from homogenization.cli import plot, posterior_flags
from homogenization.cli.options import (
    add_alpha0_argument,
    add_backend_list_argument,
    add_cell_arguments,
    add_checkpoint_arguments,
    add_critical_state_argument,
    add_orientations_argument,
    add_posterior_arguments,
    add_programme_arguments,
    add_uncertified_argument,
    add_void_ratio_arguments,
    command_parser,
)
from homogenization.cli.run_files import build_models, check_run, checkpoint_folder, refuse_programme_flags, resolve_void_ratio, resumable, run_backends, run_checkpoints, shear_iso_increment, warn_unused_alpha0
from warp_hcell.core.cli import (
    UserError,
    add_contact_law_arguments,
    contact_law_from_args,
    finite_float,
    fraction,
    positive_int,
    run_main,
    say,
    set_verbosity,
    writing_to,
)
from warp_hcell.core.files import output_folder, output_lock
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import CellDefaults, DatabaseSettings, LoadingDefaults
from warp_hcell.core.provenance import command_line

FIGURE_FILE = "cambridge.png"
COARSE_INCREMENT = DatabaseSettings.probe_max
"""Strain increment [-] above which a run is warned about: the learning database's largest
probe (the ANN extrapolates beyond it) and where the macro kinematics of every backend errs
by ~1 % of p0 (docs/dem_homogenization.md)."""
PROGRAMME_FLAGS = {"p0": "--p0", "eps_max": "--eps-max", "increment": "--increment",
                   "iso_increment": "--iso-increment", "drained": "--drained"}
"""Flags that define the built-in programme, so conflict with --programme (argparse dest -> flag)."""


def build_parser() -> argparse.ArgumentParser:
    """Parser of the biaxial command (defaults read from warp_hcell.core.parameters)."""
    cell, load = CellDefaults(), LoadingDefaults()
    parser = command_parser("homogenization.biaxial", "Isotropic compression to p0, then constant-volume (or drained) "
                                                      "biaxial shear of the H-model, or any loading programme file.")
    add_backend_list_argument(parser, "analytical")
    add_alpha0_argument(parser)
    add_void_ratio_arguments(parser)
    add_critical_state_argument(parser)
    loading_group = add_programme_arguments(
        parser, stress_unit="N/m", eps_max=load.eps_max, increment=load.increment,
        eps_max_help="axial strain at the end of the shear stage, counted from its start [-]")
    loading_group.add_argument("--drained", action="store_true", help="hold sigma22 = p0 during shear instead of constant volume")
    parser.add_argument("--programme", type=Path, default=None,
                        help="JSON or TOML loading programme (format of homogenization.element_test.programme.to_dict; "
                             "docs/programmes.md, examples in homogenization/data/programmes/)")
    add_orientations_argument(parser, cell.n_orientations)
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
    add_posterior_arguments(parser)
    add_checkpoint_arguments(parser)
    return parser


def run_mesostructure(args: argparse.Namespace) -> Mesostructure:
    """The cell of the run: --mesostructure built at --alpha0 and --radius, else the H-cell of --alpha0 and --radius.

    Raises:
        warp_hcell.mesostructures.mesostructure.MesostructureError: a file or spec that does not build (one line).
        UserError: a 3D cell (one line).
    """
    if args.mesostructure is None:
        return h_cell(args.alpha0, args.radius)
    meso = args.mesostructure.build(args.alpha0, args.radius)
    if meso.dim != 2:
        raise UserError(f"--mesostructure {args.mesostructure.text}: a 3D cell; hmodel biaxial runs planar cells "
                        f"(e.g. hcell:alpha0=55), hmodel triaxial 3D ones")
    return meso


def build_programme(args: argparse.Namespace, argv: Sequence[str]) -> tuple[programmes.Programme, dict[str, Any]]:
    """The programme of the run: the ``--programme`` file, else the built-in biaxial test.

    Returns:
        (programme, the resolved built-in settings p0, eps_max, increment, iso_increment,
        or the programme file name).

    Raises:
        UserError: built-in programme flags given with --programme, or an increment larger
            than --eps-max (it would be silently cut to one increment).
    """
    if args.programme is not None:
        refuse_programme_flags(build_parser(), argv, PROGRAMME_FLAGS)
        return programmes.read_programme(args.programme), {"programme_file": str(args.programme)}
    p0, eps_max, increment = args.p0, args.eps_max, args.increment
    iso_increment = shear_iso_increment(args, f": the shear stage would be one increment of {eps_max:g}; "
                                              f"use an increment <= {COARSE_INCREMENT:g}")
    settings = {"p0": p0, "eps_max": eps_max, "increment": increment, "iso_increment": iso_increment}
    return programmes.biaxial(p0, eps_max, increment, iso_increment=iso_increment, drained=args.drained), settings


def coarse_steps(programme: programmes.Programme) -> list[tuple[str, float]]:
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


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    command = command_line() if argv is None else shlex.join(["hmodel", "biaxial", *argv])
    out: Path = args.out
    argv_given = sys.argv[1:] if argv is None else argv
    calibrated = posterior_flags.apply_posterior(args, argv_given, build_parser(), dim=2)
    density_map = resolve_void_ratio(args, argv_given, build_parser(), dim=2)
    critical_state = posterior_flags.critical_state(calibrated, args, 2)
    check_run(args, FIGURE_FILE, posterior_flags.BAND_FILE)
    programme, settings = build_programme(args, argv_given)
    posterior_flags.check_band_test(calibrated, settings, "--fabric-anisotropy" if args.fabric_anisotropy else "")
    if args.normalise and not any(step.stop_at_p for step in programme):
        raise UserError("--normalise needs p0: the programme has no stop_at_p step")
    for label, largest in coarse_steps(programme):
        warn(f"step {label!r} has strain increments up to {largest:g} > {COARSE_INCREMENT:g}: coarse kinematics "
             f"(~1 % of p0 and more){'; the ANN extrapolates beyond its training probes' if 'ann' in args.backend else ''}")
    law = contact_law_from_args(args)
    if args.verbose:
        say(f"programme: {programmes.to_dict(programme)}", f"contact law: {law.to_dict()}, radius {args.radius:g} m")

    meso = run_mesostructure(args)
    warn_unused_alpha0(build_parser(), argv_given, args.mesostructure)
    with output_lock(out):
        models, options = build_models(args, law, meso)
        checkpoints = run_checkpoints(args, models, options, law, meso, programme)
        drained = figures.is_drained({"drained": args.drained or None}, programme)
        p0 = next((s.stop_at_p for s in programme if s.stop_at_p is not None), None)
        with resumable(out, checkpoints), output_folder(out) as work:
            records, stored, written = run_backends(
                args, models, options, law, meso,
                run=lambda model, checkpoint: driver.run(model, programme, mesostructure=meso, n_orientations=args.orientations,
                                             fabric_anisotropy=args.fabric_anisotropy,
                                             fabric_direction_deg=args.fabric_direction,
                                             snapshot_interval=args.snapshot_interval or 0,
                                             void_ratio=args.void_ratio, density_map=density_map,
                                             critical_state=critical_state, progress=stage_bars,
                                             checkpoint=checkpoint),
                parameters=lambda record: {
                    "p0": p0,
                    **settings,
                    "n_orientations": args.orientations,
                    "fabric_anisotropy": args.fabric_anisotropy,
                    "fabric_direction_deg": args.fabric_direction,
                    "drained": drained,
                    "stress_rtol": LoadingDefaults.stress_rtol,
                    "mesostructure": args.mesostructure.text if args.mesostructure is not None else None,
                    **posterior_flags.run_record(calibrated),
                    "void_ratio": args.void_ratio,
                    "density_map": None if density_map is None else density_map.to_dict(),
                    **({} if critical_state is None else {"critical_state": asdict(critical_state)}),
                },
                work=work, command=command, checkpoints=checkpoints)
            posterior_flags.compute_band(calibrated, dim=2, drained=args.drained, p0=args.p0, eps_max=args.eps_max)
            with writing_to(out):
                band_line = posterior_flags.write_band(calibrated, work)
            runs = {name: figures.Run(record, stored[name]) for name, record in records.items()}
            slopes = (figures.critical_state_lines(list(runs.values()), list(runs), warn, report=say)
                      if args.csl else None)
            fig = figures.overlay_figure(list(runs.values()), fourth=args.fourth_panel, deviator=args.deviator,
                                          normalise=args.normalise, csl=slopes)
            scale = 1.0 / args.p0 if args.normalise else 1.0
            posterior_flags.shade(fig, calibrated, (
                (0, "q", scale * (0.5 if args.deviator == "t" else 1.0)),
                (2, "eps_v", 100.0) if drained else (2, "p", scale)))
            with writing_to(out):
                figures.save_figure(fig, work / FIGURE_FILE)
        shutil.rmtree(checkpoint_folder(out), ignore_errors=True)  # the run is in place: its checkpoints are spent
    say(*written, *([band_line.replace(posterior_flags.BAND_FILE, str(out / posterior_flags.BAND_FILE))]
                    if band_line else []),
        f"figure -> {out / FIGURE_FILE}" + (f" ({plot.csl_summary(slopes)})" if slopes is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
