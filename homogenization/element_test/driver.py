"""Run a loading programme on a set of oriented cells: ``run(cell_model, programme) -> Record``.

The driver runs one material point of the homogenised material from the touching state through
the element-test engine (``homogenization.element_test``): the point's oriented cells
(``element_test.points``), the programme's steps as stages (``element_test.plan``), the
stress-controlled components solved by the engine's one stress-control solver under its strict
policy (``element_test.solver``: Newton on the consistent tangent, a linear predictor from the last
tangent, bisection and jump detection with one controlled component, Broyden updates between fresh
tangents with several in 3D and, where they do not converge, jump detection by bisection on the worst
component; a failure raises ``ControlError``), and the history recorded
(``element_test.record``). Convergence: every controlled stress within ``stress_rtol`` times its
``|target|`` (times the largest ``|sigma|`` recorded so far where the target is zero).

The same driver runs 3D (triaxial) programmes, whose steps control (11, 22, 33)
(``programme.COMPONENTS_3D``), on cells of dimension 3 oriented by ``homogenization.material.orientation``
(``HomogenisedMaterial``): p = tr(sigma) / 3 and q = sqrt(3 J2) (``invariants``), stresses in Pa
and the volume in m^3. A step's ``coupling`` makes the stress-controlled components also follow
sigma11 (constant p, constant b): the residual of component i is sigma_i - c_i (sigma11 - sigma11 at
the start of the step) - its ramped target.

It imports the cell-model protocol only, never a backend. Sign convention: compression
and contraction positive; stresses [N/m] (2D) or [Pa] (3D), strains [-], macro shear strain always zero.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import Any, Callable, Literal, Mapping, Sequence

import numpy as np

from homogenization.element_test import checkpoint as checkpoint_mod
from homogenization.element_test.checkpoint import RunCheckpoint
from homogenization.element_test.points import MaterialPoints, material_points
from homogenization.material.critical_state import CriticalState, Renewal
from homogenization.material.density import DensityMap, default_map
from homogenization.element_test.record import History, Record
from homogenization.element_test.stages import StageProgress, run_stages
from homogenization.element_test.solver import JUMP_WIDTH, STRICT, ControlError, StressControl
from homogenization.element_test.programme import Programme, dimension, validate
from warp_hcell.core.contract import CellModel
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import CellDefaults, LoadingDefaults

__all__ = ["JUMP_WIDTH", "LEBEDEV_ORDER", "N_SPINS", "ControlError", "Record", "RunCheckpoint", "run", "to_record"]

LEBEDEV_ORDER = 53
"""Default Lebedev order of the 3D cell axes (``orientation``: 487 axes on the hemisphere).
With ``N_SPINS`` staggered spins (7792 cells) doubling the spins moves the closed form's
triaxial curves by at most 0.08 % of p0 and doubling the axes (order 77) by at most 0.46 %,
also where undrained samples at 2e5 Pa dilate to 20-30 p0 (docs/triaxial.md, Quadrature;
orders 35 and 47 missed there by up to 3.3 % and 1.1 %)."""
N_SPINS = 16
"""Default spins per 3D cell axis, equally spaced over the cell's spin period and staggered from
axis to axis (``orientation``)."""


def _diagnosed(exc: ControlError, points: MaterialPoints, programme: Programme, mesostructure: Any) -> ControlError:
    """``exc`` with the cell model's one-line diagnosis of the failed stress control appended (its
    ``control_diagnosis``, e.g. ``homogenization.ann.cell.AnnCell``) at the last trial from the last
    accepted state, where the model has one and a trial was made."""
    diagnose = getattr(points.model, "control_diagnosis", None)
    if diagnose is None or points.last_trial is None:
        return exc
    diagnosis = diagnose(points.state.cells, points.material.localise(points.last_trial), points.axes(), programme,
                         mesostructure)
    return exc if diagnosis is None else ControlError(f"{exc}; {diagnosis}")


def run(
    cell_model: CellModel,
    programme: Programme,
    *,
    mesostructure: Mesostructure,
    n_orientations: int = CellDefaults.n_orientations,
    fabric_anisotropy: float = 0.0,
    fabric_direction_deg: float = 0.0,
    snapshot_interval: int = 0,
    stress_rtol: float = LoadingDefaults.stress_rtol,
    max_newton_iterations: int = LoadingDefaults.max_newton_iterations,
    progress: StageProgress | Literal[False] | None = None,
    lebedev_order: int = LEBEDEV_ORDER,
    n_spins: int = N_SPINS,
    spin_period_deg: float | None = None,
    staggered_spins: bool = True,
    before_stage: Mapping[int, Callable[[MaterialPoints], None]] | None = None,
    critical_state: CriticalState | None = None,
    void_ratio: float | None = None,
    density_map: DensityMap | None = None,
    renewal: Callable[[MaterialPoints], Any] | None = None,
    checkpoint: RunCheckpoint | None = None,
) -> Record:
    """The ``Record`` of ``programme`` run on the oriented cells of ``cell_model``, all starting as ``mesostructure``.

    Args:
        n_orientations, fabric_anisotropy, fabric_direction_deg: planar orientations
            (``orientation.orientations``).
        lebedev_order, n_spins, spin_period_deg, staggered_spins: 3D orientations
            (``orientation.orientations_3d``; spin_period_deg None: the cell's own).
        snapshot_interval: per-cell observables every this many increments (0: stage ends).
        stress_rtol, max_newton_iterations: stress control's tolerance [-], step calls per increment.
        progress: per-stage callbacks (``stages.StageProgress``) or None/False.
        before_stage: step index -> action on the material point before it.
        critical_state: renewal rule of the cells (``material.critical_state``; None: none), counted in
            diagnostics ``critical_state_*``.
        void_ratio, density_map: the cells' initial void ratio [-] (``Record.e0``) and its map (None: the
            default); the cell must be at the map's alpha0.
        renewal: points -> their renewal, replacing ``critical_state``'s (a ``clip_log``: diagnostics
            ``interlocking_*``).
        checkpoint: where the run saves itself and resumes from (``element_test.checkpoint``).

    Raises:
        ValueError: invalid programme or options.
        ControlError: an unsolved stress-controlled increment.
        UserError: a checkpoint of other settings, or unreadable.
    """
    programme = validate(programme)
    if progress is True:
        raise TypeError("progress=True: pass a callback (homogenization.cli.progress.stage_bars draws bars)")
    if snapshot_interval < 0:
        raise ValueError(f"snapshot_interval = {snapshot_interval} must be >= 0")
    dim = dimension(programme)
    meso_dim = getattr(mesostructure, "dim", 2)
    if meso_dim != dim:
        raise ValueError(f"the programme controls {dim} components but mesostructure {mesostructure.name!r} is a "
                         f"{meso_dim}D cell")
    density_map = _void_ratio_map(mesostructure, dim, void_ratio, density_map)
    points = material_points(cell_model, mesostructure, 1, n_orientations=n_orientations,
                             fabric_anisotropy=fabric_anisotropy, fabric_direction_deg=fabric_direction_deg,
                             lebedev_order=lebedev_order, n_spins=n_spins, spin_period_deg=spin_period_deg,
                             staggered_spins=staggered_spins)
    if renewal is not None:
        points.renewal = renewal(points)
    elif critical_state is not None:
        points.renewal = Renewal(critical_state, points.material, points.state, density_map)
    solver = StressControl(points, replace(STRICT, rtol=stress_rtol, max_iterations=max_newton_iterations))
    history = History(sum(s.n_increments for s in programme), 1, dim)
    resume = None
    if checkpoint is not None:
        why = checkpoint_mod.supports(points, before_stage)
        if why is not None:
            warnings.warn(f"this run keeps no checkpoint: {why}", RuntimeWarning, stacklevel=2)
            checkpoint = None
        elif checkpoint.exists():
            checkpoint.check()
            resume = checkpoint.load(solver, history)
    try:
        step_seconds, _, _ = run_stages(solver, programme, history, snapshot_interval=snapshot_interval,
                                     progress=progress or None, before_stage=before_stage, checkpoint=checkpoint,
                                     resume=resume)
    except ControlError as exc:
        raise _diagnosed(exc, points, programme, mesostructure) from None
    k = history.k
    jumps = int(np.nansum(history.diagnostics.get("stress_control_jump", np.zeros(0))[:k]))
    if jumps:
        warnings.warn(f"stress control met a jump of the response across its target at {jumps} increment(s): the "
                      f"side nearer the target was accepted (diagnostics 'stress_control_jump')", RuntimeWarning,
                      stacklevel=2)
    _record_counts(history, getattr(points.renewal, "log", None), "critical_state",
                   ("renewals", "rate_capped", "angle_clipped", "merged"))
    _record_counts(history, getattr(points.renewal, "clip_log", None), "interlocking", ("floored", "fallbacks"))
    record = to_record(history, points, programme, step_seconds, dict(mesostructure.parameters))
    if density_map is not None:
        record.e0, record.density_map = float(void_ratio), density_map
    return record


def _record_counts(history: History, log: Sequence[tuple[np.ndarray, ...]] | None, prefix: str,
                   names: Sequence[str]) -> None:
    """Diagnostics ``<prefix>_<name>`` of the one point's running counts that ``log`` holds per accepted increment
    (tuples of arrays (n_points,) in ``names``' order), NaN on the rows after them; nothing where ``log`` is None."""
    if log is None:
        return
    pad = [np.nan] * (history.rows.shape[0] - len(log))
    for i, name in enumerate(names):
        history.diagnostics[f"{prefix}_{name}"] = np.array([float(c[i][0]) for c in log] + pad)


def _void_ratio_map(mesostructure: Mesostructure, dim: int, void_ratio: float | None,
                    density_map: DensityMap | None) -> DensityMap | None:
    """The map of a run given ``void_ratio`` (``density_map``, else the default of ``dim``); None without one.

    Raises:
        ValueError: ``density_map`` without ``void_ratio``, or a cell not at the map's alpha0 (1e-6 deg).
        UserError: a void ratio outside the map.
    """
    if void_ratio is None:
        if density_map is not None:
            raise ValueError("density_map is given without void_ratio")
        return None
    density_map = default_map(dim) if density_map is None else density_map
    alpha0 = density_map.alpha0_deg(void_ratio)
    cell = mesostructure.parameters.get("alpha0_deg")
    if cell is None or abs(float(cell) - alpha0) > 1e-6:
        raise ValueError(f"void ratio {void_ratio:g} maps to alpha0 = {alpha0:.9g} deg, but the mesostructure "
                         f"{mesostructure.name!r} has alpha0 = {cell} deg; build it at the map's alpha0")
    return density_map


def to_record(history: History, points: MaterialPoints, programme: Programme, step_seconds: np.ndarray,
              parameters: dict[str, float]) -> Record:
    """The ``Record`` of the first material point of ``points`` whose run ``history`` holds; ``parameters``: the
    mesostructure's named parameters."""
    k, dim, orient = history.k, points.dim, points.material.orient
    rows = history.rows[:k, 0]
    V0 = float(points.material.V0[0])
    label_array = np.array([s.label for s in programme])
    space = points.dimension
    stress = rows[:, dim:dim + space.n_voigt]
    strain = {f"eps{c}": rows[:, a].copy() for a, c in enumerate(space.normal_components)}
    sigma = {f"sigma{c}": stress[:, m].copy() for m, c in enumerate(space.components)}
    model = points.model
    return Record(
        stage=label_array[history.stage_index[:k]],
        **strain,
        **sigma,
        p=space.mean_stress(stress),
        q=space.deviator(stress),
        J=rows[:, -1].copy(),
        volume=V0 * rows[:, -1],
        newton_iterations=history.iterations[:k].copy(),
        diagnostics={name: v[:k].copy() for name, v in history.diagnostics.items()},
        snapshot_increment=np.array(history.snap_k, dtype=np.int64),
        snapshot_stage=label_array[np.array(history.snap_stage, dtype=np.int64)],
        snapshots=_snapshots(history.snaps),
        theta_deg=orient.axis_angle_deg,
        frames=orient.recorded_frames,
        weights=np.array(orient.weights),
        V0=V0,
        parameters=parameters,
        backend=str(getattr(model, "name", type(model).__name__)),
        programme=programme,
        final_state={name: np.array(v) for name, v in model.state_to_arrays(points.state.cells).items()},
        step_seconds=step_seconds,
    )


def _snapshots(snaps: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Per-cell observables of the snapshots, name -> shape (m, n_cells). Where the cells changed during the
    run (an erosion) and so their observables, every name is float with NaN in the snapshots without it."""
    names = list(dict.fromkeys(name for snap in snaps for name in snap))
    if all(len(snap) == len(names) for snap in snaps):
        return {name: np.stack([snap[name] for snap in snaps]) for name in names}
    out = {}
    for name in names:
        like = next(snap[name] for snap in snaps if name in snap)
        dtype = np.result_type(like, np.float64)
        out[name] = np.stack([snap[name].astype(dtype) if name in snap else np.full(like.shape, np.nan)
                              for snap in snaps])
    return out
