"""python -m homogenization.bvp --backend analytical --alpha0 40 --p0 5.85e6 --eps-max 0.05 --increment 1e-3 --orientations 72 --elements 4,8 [--imperfection F] --out DIR

Plane-strain biaxial specimen of the homogenised H-model by finite elements
(``homogenization.fe.solver``, scikit-fem): every Gauss point is a material point with its own
cells (``homogenization.material.homogenised``), all stepped in one batch per Newton iteration. Stage 1:
the lateral pressure and the stress of the top platen rise together to p0 in --iso-steps
steps; stage 2: the smooth rigid top platen moves down by --increment H per step (lateral
pressure p0) to eps1 = --eps-max, counted from the end of stage 1.

--imperfection F (in [0, 1); 0 = homogeneous) gives the elements that touch the middle of the
left face or whose centre lies within W/4 of it (a zone of nearly fixed size, so it does not
shrink with the mesh) the looser opening angle alpha0 + F (90 deg - alpha0). A softening local model localises in a band
whose width is set by the mesh: results after the peak depend on --elements. The cells start
from the H-cell of --alpha0 (``warp_hcell.mesostructures.hcell.h_cell``), or from --mesostructure (a
file or a builder spec, built at --alpha0 unless it gives its own); the weak zone's cells are
built at the looser angle, which needs a cell built from an opening angle.

--length L [m] regularises the specimen by a local second-gradient continuum
(``homogenization.fe.second_gradient``: D = E_ref L^2, E_ref the material point's shear modulus
at p0), which sets the band width by L instead of the mesh; without it the plain
first-gradient solver runs. --checkpoint-every N saves DIR/checkpoint.h5 every N steps;
--resume continues a killed run from it (same flags; the result is the uninterrupted run's).
--reuse-tangent (a backend that computes its tangent apart from the step: the DEM) lets Newton
corrections reuse the last tangent computed, also from earlier steps, while it contracts
(``homogenization.fe.solver.BiaxialSpecimen``); the curve moves by about the Newton tolerance.

Writes DIR/curve.csv (stage,eps11,eps22,sigma11,sigma22,sigma12,p,q,iterations; 1 = axial),
DIR/run.h5 (fields per step), DIR/vtu/step_NNNN.vtu with DIR/specimen.pvd (ParaView) and
DIR/bvp.png (see ``homogenization.fe.output``). --compare also runs the material point of
``homogenization.element_test.driver`` on the drained biaxial programme with the same settings and overlays
it (the homogeneous specimen should coincide with it).

Sign convention: compression and contraction positive; stresses in N/m (2D). Bad input
(non-positive element counts, imperfection outside [0, 1), unknown backend, alpha0 outside
[30, 90) deg, a mesostructure the backend does not model, --imperfection with a cell of fixed
geometry, existing output without --overwrite, --length <= 0 or too large an element for it, a
backend without tangent, --resume without a checkpoint or with other flags) is one line on
stderr and exit code 2, before any step.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import Sequence, TYPE_CHECKING

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.material import orientation
from homogenization.cli.options import (add_alpha0_argument, add_backend_argument, add_cell_arguments,
                                        add_orientations_argument, add_uncertified_argument, certificate_note,
                                        command_parser, refuse_uncertified)
from homogenization.backends import make_cell_model
from homogenization.cli.run_files import backend_options, check_models_take, check_options
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.core.cli import (
    UserError,
    axial_strain,
    fraction,
    positive_float,
    positive_int,
    progress_bar,
    quiet_warp,
    run_main,
    say,
    set_verbosity,
    writing_to,
)
from warp_hcell.core.files import check_output_path
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.mesostructure import Mesostructure

if TYPE_CHECKING:
    from homogenization.fe import solver as fe
from warp_hcell.core.parameters import ALPHA_MAX_DEG, CellDefaults, ContactLaw, FeDefaults


CHECKPOINT_FILE = "checkpoint.h5"
"""Checkpoint of a run in its output folder (``homogenization.fe.checkpoint``)."""
MIN_ELEMENTS_ACROSS_BAND = 3.0
"""Fewest elements across the expected band width that --length accepts [-]."""


def check_regularisation(args: argparse.Namespace) -> None:
    """UserError (one line) where the mesh is too coarse for --length: fewer than
    ``MIN_ELEMENTS_ACROSS_BAND`` elements across the expected band (``second_gradient.expected_band_width``)."""
    if args.length is None:
        return
    from homogenization.fe.second_gradient import expected_band_width  # noqa: PLC0415 (scikit-fem)
    nx, ny = args.elements
    h = max(FeDefaults.width / nx, FeDefaults.height / ny)
    width = expected_band_width(args.length)
    if width < MIN_ELEMENTS_ACROSS_BAND * h:
        raise UserError(f"--length {args.length:g}: the expected band ({width:.3g} m wide) spans {width / h:.1f} "
                        f"elements of {h:.3g} m; use at least {MIN_ELEMENTS_ACROSS_BAND:g} (finer --elements or "
                        f"a larger --length)")


def element_counts(text: str) -> tuple[int, int]:
    """argparse type: "NX,NY", two integers >= 1."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not NX,NY")
    try:
        counts = tuple(positive_int(part.strip()) for part in parts)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"element counts {text!r}: {exc}") from None
    return counts  # type: ignore[return-value]


def build_parser() -> argparse.ArgumentParser:
    """Parser of the bvp command (defaults read from warp_hcell.core.parameters)."""
    cell, bvp = CellDefaults(), FeDefaults()
    parser = command_parser("homogenization.bvp", "Plane-strain biaxial specimen of the homogenised H-model by finite "
                                                  "elements.")
    add_backend_argument(parser)
    add_alpha0_argument(parser)
    parser.add_argument("--p0", type=positive_float, default=cell.p0, help="confining pressure [N/m], > 0")
    parser.add_argument("--eps-max", type=axial_strain, default=bvp.eps_max,
                        help="axial strain at the end of the shear stage, counted from its start [-]")
    parser.add_argument("--increment", type=positive_float, default=bvp.increment,
                        help="axial strain of one shear step (platen displacement / H) [-]")
    parser.add_argument("--iso-steps", type=positive_int, default=bvp.iso_steps, help="load steps of the isotropic stage")
    add_orientations_argument(parser, bvp.n_orientations, "cell orientations per Gauss point")
    parser.add_argument("--elements", type=element_counts, default=",".join(map(str, bvp.elements)),
                        help="elements NX,NY across the width and along the height, each >= 1")
    parser.add_argument("--imperfection", type=fraction, default=0.0,
                        help="F in [0, 1): weak zone at mid-height of the left face with alpha0 + F (90 - alpha0); 0 = homogeneous")
    parser.add_argument("--newton-rtol", type=positive_float, default=bvp.newton_rtol,
                        help="Newton tolerance: out-of-balance force norm / (p0 W) [-] (the DEM's own equilibrium "
                             "tolerance limits it: use ~1e-5 with --backend dem)")
    parser.add_argument("--reuse-tangent", action="store_true",
                        help="dem: Newton corrections reuse the last tangent computed, across steps, while it "
                             "cuts the residual tenfold per correction (fewer tangents, a few more updates)")
    parser.add_argument("--length", type=positive_float, default=None,
                        help="material length L [m] of the local second-gradient regularisation (D = E_ref L^2, "
                             "E_ref the material's shear modulus at p0); none: the plain first-gradient solver")
    parser.add_argument("--checkpoint-every", type=positive_int, default=None,
                        help=f"save DIR/{CHECKPOINT_FILE} every N load steps (and after the last)")
    parser.add_argument("--resume", action="store_true",
                        help=f"continue the run of DIR from DIR/{CHECKPOINT_FILE} (same flags)")
    parser.add_argument("--compare", action="store_true",
                        help="also run the material point (driver, drained biaxial) and overlay it")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    add_cell_arguments(parser, "the cell (analytical: the plain H-cell only; ann: the model's mesostructure); "
                               "default: the H-cell of --alpha0.", "CPU threads of the DEM (dem only)")
    add_uncertified_argument(parser)
    return parser


def _tangent_note(results: Sequence[fe.StepResult]) -> str:
    """"; tangents computed N, reused M" (diagnostics of ``fe.BiaxialSpecimen.solve_step``)."""
    if not results or "tangents" not in results[0].diagnostics:
        return ""
    computed = int(sum(r.diagnostics.get("tangents", 0) for r in results))
    return f"; tangents computed {computed}, reused {int(sum(r.diagnostics.get('tangents_reused', 0) for r in results))}"


def _halving_note(results: Sequence[fe.StepResult]) -> str:
    """The run's Newton corrections halved because the residual grew, and the iterates taken though it grew."""
    halved, taken = (int(sum(r.diagnostics.get(name, 0) for r in results)) for name in ("line_search_halvings",
                                                                                          "growths_taken"))
    return f"corrections halved (residual grew): {halved}, taken though it grew: {taken}"


def _material_note(results: Sequence[fe.StepResult]) -> str:
    """The backend's counts that fired at the steps' converged updates, summed over steps (``fe_output.material_counts``;
    run.h5's ``history/material_*`` per step); "" where none fired."""
    from homogenization.fe import output as fe_output  # noqa: PLC0415 (scikit-fem)

    totals = {name: sum(r.diagnostics.get(name, 0.0) for r in results) for name in fe_output.material_counts(results)}
    fired = ", ".join(f"{name} {value:.6g}" for name, value in totals.items() if value)
    return f"backend counts at the converged updates, summed over steps: {fired}" if fired else ""


def _solver_note(results: Sequence[fe.StepResult]) -> str:
    """"; second-gradient solves: N LU factorisations (M redone with pivoting), K GMRES iterations" (the
    specimen's ``solver_counts``, per step in ``fe.StepResult.diagnostics``); "" for a first-gradient run."""
    if not results or "pivoted_factorisations" not in results[0].diagnostics:
        return ""
    total = {name: int(sum(r.diagnostics[name] for r in results))
             for name in ("factorisations", "pivoted_factorisations", "krylov_iterations")}
    return (f"; second-gradient solves: {total['factorisations']} LU factorisations ({total['pivoted_factorisations']} "
            f"redone with pivoting), {total['krylov_iterations']} GMRES iterations")


def weak_elements(specimen: fe.BiaxialSpecimen) -> np.ndarray:
    """Elements touching the middle of the left face (0, H/2) or whose centre lies within W/4 of it.

    Returns:
        bool, shape (n_elements,); at least one element on any mesh.
    """
    centre = specimen.element_centroids()
    corners = specimen.mesh.p[:, specimen.mesh.t]  # (2, 4, n_elements)
    mid = 0.5 * specimen.height
    touching = (corners[0].min(axis=0) <= 0.0) & (corners[1].min(axis=0) <= mid) & (corners[1].max(axis=0) >= mid)
    return touching | (np.hypot(centre[:, 0], centre[:, 1] - mid) < 0.25 * specimen.width)


def element_mesostructures(args: argparse.Namespace, weak: np.ndarray) -> tuple[Mesostructure, Mesostructure | None]:
    """The cell of the sound elements, and of the ``weak`` ones (None where no element is weak).

    The weak cell is built at alpha0 + F (90 deg - alpha0) from the H-cell or from a builder spec
    without its own alpha0.

    Raises:
        UserError: weak elements and a mesostructure of fixed geometry (a file, or a spec with alpha0).
        warp_hcell.mesostructures.mesostructure.MesostructureError: a mesostructure that does not build.
    """
    source = args.mesostructure
    sound = h_cell(args.alpha0, CellDefaults.radius) if source is None else source.build(args.alpha0)
    if not weak.any():
        return sound, None
    if source is not None and not source.takes_alpha0:
        raise UserError(f"--imperfection builds the weak zone's cells at a looser alpha0: --mesostructure {source} "
                        f"fixes its geometry (use the H-cell or a builder spec without alpha0)")
    weak_alpha0 = args.alpha0 + args.imperfection * (ALPHA_MAX_DEG - args.alpha0)
    return sound, (h_cell(weak_alpha0, CellDefaults.radius) if source is None else source.build(weak_alpha0))


def _alpha0_or_nan(meso: Mesostructure | None) -> float:
    """The parameter alpha0_deg [deg] of a cell (``Mesostructure.parameters``); NaN for a cell without it or no cell."""
    alpha0 = None if meso is None else meso.parameters.get("alpha0_deg")
    return float("nan") if alpha0 is None else alpha0


def material_point_reference(model, meso: Mesostructure, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Drained biaxial material point of ``meso`` with the same settings, from the end of its isotropic stage."""
    programme = programmes.biaxial(args.p0, args.eps_max, args.increment, drained=True)
    record = driver.run(model, programme, mesostructure=meso, n_orientations=args.orientations, progress=False)
    start = int(np.flatnonzero(record.stage != "shear")[-1])
    keep = slice(start, None)
    eps_v = record.eps11 + record.eps22
    return {"eps1": record.eps11[keep] - record.eps11[start], "q": record.q[keep], "p": record.p[keep],
            "eps_v": eps_v[keep] - eps_v[start]}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    from homogenization.output import run_labels  # noqa: PLC0415 (matplotlib: only when the command runs)
    from homogenization.fe import output as fe_output, second_gradient, solver as fe  # noqa: PLC0415 (scikit-fem)
    from homogenization.fe.checkpoint import Checkpoint  # noqa: PLC0415 (scikit-fem)

    out: Path = args.out
    checkpoint_path = out / CHECKPOINT_FILE
    if args.resume:
        if not checkpoint_path.is_file():
            raise UserError(f"--resume: {checkpoint_path} does not exist")
    else:
        check_output_path(out, overwrite=args.overwrite)
    check_regularisation(args)
    check_options(args, (args.backend,))
    if args.backend == "dem" and not args.verbose:
        quiet_warp(args.device)
    model = make_cell_model(args.backend, contact_law=ContactLaw(), radius=CellDefaults.radius,
                            **backend_options(args, args.backend))
    refuse_uncertified(model, args)
    nx, ny = args.elements
    if args.length is None:
        specimen = fe.BiaxialSpecimen(nx, ny, newton_rtol=args.newton_rtol, reuse_tangent=args.reuse_tangent)
    else:
        specimen = second_gradient.SecondGradientSpecimen(nx, ny, length=args.length, modulus=1.0,
                                                          newton_rtol=args.newton_rtol,
                                                          reuse_tangent=args.reuse_tangent)
    weak = weak_elements(specimen) if args.imperfection > 0.0 else np.zeros(specimen.mesh.nelements, bool)
    sound, weak_meso = element_mesostructures(args, weak)
    for meso in (sound, weak_meso):
        if meso is not None:  # a mesostructure the backend does not model fails here, before the run
            check_models_take({args.backend: model}, meso)
    element_alpha0 = np.where(weak, _alpha0_or_nan(weak_meso), _alpha0_or_nan(sound))
    point_meso = sound if weak_meso is None else [weak_meso if w else sound
                                                  for w in np.repeat(weak, specimen.points_per_element())]
    material = HomogenisedMaterial(model, orientation.orientations(args.orientations), point_meso, specimen.n_points)
    if not material.returns_tangent:
        raise UserError(f"backend {args.backend!r} returns no consistent tangent in this version")
    n_shear = programmes.n_increments_for(args.eps_max, args.increment)
    steps = fe.isotropic_stage(args.p0, args.iso_steps) + fe.shear_stage(args.p0, n_shear * args.increment, n_shear)
    modulus = None
    if args.length is not None:
        point = HomogenisedMaterial(model, orientation.orientations(args.orientations), sound, 1)
        try:
            modulus = second_gradient.reference_modulus(point, args.p0)
        except ValueError as exc:
            raise UserError(f"--length: {exc}") from None
        specimen.set_modulus(modulus)

    parameters = {
        "backend": args.backend, "alpha0_deg": sound.parameters.get("alpha0_deg"), "p0": args.p0, "eps_max": args.eps_max,
        "increment": args.increment, "iso_steps": args.iso_steps, "n_orientations": args.orientations,
        "elements": [nx, ny], "imperfection": args.imperfection, "n_weak_elements": int(weak.sum()),
        "width": specimen.width, "height": specimen.height, "newton_rtol": specimen.newton_rtol,
        "contact_law": asdict(ContactLaw()), "radius": CellDefaults.radius,
        "mesostructure": args.mesostructure.text if args.mesostructure is not None else None,
        "length": args.length, "reference_modulus": modulus,
        "second_gradient_modulus": None if modulus is None else modulus * args.length ** 2,
        "reuse_tangent": specimen.reuse_tangent,
    }
    checkpoint = None
    if args.checkpoint_every is not None or args.resume:
        # the interval sets when solver data are renewed (``fe.REFRESH_EVERY``): a resume keeps it, for the same bits
        settings = {**{k: v for k, v in parameters.items() if k != "ann_certificate"},
                    "checkpoint_every": args.checkpoint_every}
        checkpoint = Checkpoint(checkpoint_path, args.checkpoint_every or len(steps), settings)
        if args.resume:
            checkpoint.check()
        else:
            out.mkdir(parents=True, exist_ok=True)
            checkpoint_path.unlink(missing_ok=True)  # an old run's (--overwrite): never resumed from

    start = time.perf_counter()
    done = checkpoint.steps_done() if args.resume else 0
    if done:
        say(f"resuming from {checkpoint_path} after step {done} of {len(steps)}")
    with progress_bar(total=len(steps), initial=done, desc="bvp", unit="step", leave=False) as bar:
        def progress(k: int, result: fe.StepResult) -> None:
            bar.set_postfix_str(f"{result.stage}, q/p0 {(result.sigma11 - result.sigma22) / args.p0:.4f}, "
                                f"{result.iterations} its, residual {result.residuals[-1]:.2e} N/m", refresh=False)
            bar.update(1)
        try:
            results = specimen.run(material, steps, scale=args.p0, progress=progress, checkpoint=checkpoint)
        except fe.NewtonError as exc:
            raise UserError(str(exc)) from None
    elapsed = time.perf_counter() - start
    updates = sum(r.iterations + 1 for r in results[done:])
    reference = material_point_reference(model, sound, args) if args.compare else None

    if hasattr(model, "certificate_problem"):
        parameters["ann_certificate"] = {"certified": model.certificate_problem is None,
                                         "worst": None if model.certificate is None else model.certificate.worst,
                                         "problem": model.certificate_problem}
    kind = "homogeneous" if not weak.any() else f"imperfection F = {args.imperfection:g} in {int(weak.sum())} elements"
    if args.length is not None:
        kind += f", second gradient L = {args.length:g} m"
    title = f"{run_labels.title(run_labels.describe(parameters))}, {nx} × {ny} elements, {kind}"
    with writing_to(out):
        paths = fe_output.write_outputs(out, specimen, results, element_alpha0, parameters, args.seed, title, reference)
    shear_iterations = [r.iterations for r in results if r.stage == "shear"] or [0]
    say(f"{len(results) - done} steps in {elapsed:.1f} s{certificate_note(model)}: {updates} material updates of {specimen.n_points} points "
        f"({updates * specimen.n_points / elapsed:.3g} material-point updates/s, "
        f"{updates * material.n_cells / elapsed:.3g} cell-steps/s); "
        f"Newton iterations per shear step: max {max(shear_iterations)}, mean {np.mean(shear_iterations):.2f}; "
        + _halving_note(results) + _tangent_note(results) + _solver_note(results))
    fired = _material_note(results)
    if fired:
        say(fired)
    if reference is not None and not weak.any():
        table = fe_output.curve_table(results)
        shear = np.flatnonzero(table["stage"] == "shear")
        q_fe = np.concatenate([[table["q"][shear[0] - 1]], table["q"][shear]]) if shear.size else table["q"]
        p_fe = np.concatenate([[table["p"][shear[0] - 1]], table["p"][shear]]) if shear.size else table["p"]
        if q_fe.size == reference["q"].size:
            say(f"vs material point: max |dq|/p0 = {np.abs(q_fe - reference['q']).max() / args.p0:.3g}, "
                f"max |dp|/p0 = {np.abs(p_fe - reference['p']).max() / args.p0:.3g}")
    say(" ".join(f"{kind} -> {path}" for kind, path in paths.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
