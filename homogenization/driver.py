"""Run a loading programme on a set of oriented cells: ``run(cell_model, programme) -> Record``.

The driver runs one material point of the homogenised material
(``homogenization.material.HomogenisedMaterial``): each macro strain increment is localised to
every cell, all cells advance with one ``cell_model.step`` call, their moments average to the
macro stress sigma = sum_k w_k S_k / (V0 J), and the history is recorded. It is the only place
where stress-controlled components are solved: Newton iterations on trial updates from the
saved state, each giving the stress and the consistent tangent of the material (one ``step``
call with the cell tangent); the first guess of an increment comes from the last tangent
computed (a linear predictor to the new target), and the first trial asks for no tangent.
Trials cost one ``step`` each because steps are pure. Convergence: every controlled stress
within ``stress_rtol`` times its ``|target|`` (times the largest ``|sigma|`` recorded so far where
the target is zero).

The same driver runs 3D (triaxial) programmes, whose steps control (11, 22, 33)
(``loading.COMPONENTS_3D``), on cells of dimension 3 oriented by ``homogenization.orientation3d``
(``HomogenisedMaterial3D``): p = tr(sigma) / 3 and q = sqrt(3 J2) (``invariants``), stresses in Pa
and the volume in m^3. A step's ``coupling`` makes the stress-controlled components also follow
sigma11 (constant p, constant b): the residual of component i is sigma_i - c_i (sigma11 - sigma11 at
the start of the step) - its ramped target.

It imports the cell-model protocol only, never a backend. Sign convention: compression
and contraction positive; stresses [N/m] (2D) or [Pa] (3D), strains [-], macro shear strain always zero.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from homogenization import orientation as orient_mod
from homogenization import orientation3d
from homogenization.invariants import deviator, deviator_3d, mean_stress, mean_stress_3d
from homogenization.loading import Programme, Step, dimension, validate
from homogenization.material import HomogenisedMaterial, HomogenisedMaterial3D, MaterialUpdate
from warp_hcell.core.contract import CellModel
from warp_hcell.core.cli import progress_bar
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import CellDefaults, LoadingDefaults

JUMP_WIDTH = 1e-6
"""Bracket width, as a fraction of the increment, below which stress control takes the
response for discontinuous at the target (``_Runner.solve_stress``) [-]: the residual still
above the tolerance there means a slope ~1e6 times the material's own (about 20 bisections)."""

LEBEDEV_ORDER = 53
"""Default Lebedev order of the 3D cell axes (``orientation3d``: 487 axes on the hemisphere).
With ``N_SPINS`` staggered spins (7792 cells) doubling the spins moves the closed form's
triaxial curves by at most 0.08 % of p0 and doubling the axes (order 77) by at most 0.46 %,
also where undrained samples at 2e5 Pa dilate to 20-30 p0 (docs/triaxial.md, Quadrature;
orders 35 and 47 missed there by up to 3.3 % and 1.1 %)."""
N_SPINS = 16
"""Default spins per 3D cell axis, equally spaced over the cell's spin period and staggered from
axis to axis (``orientation3d``)."""


class ControlError(RuntimeError):
    """A stress-controlled increment did not converge (e.g. the material cannot carry the target)."""


@dataclass
class Record:
    """History of a run, one entry per increment (the force-free initial state is implicit).

    Stresses [N/m] and strains [-] are compression/contraction positive; strains are the
    sums of the applied macro increments, counted from the initial state.

    Attributes:
        stage: stage label of each increment, shape (n,), str.
        eps11, eps22: macro strain [-], shape (n,).
        sigma11, sigma22, sigma12: macro stress [N/m], shape (n,).
        p: mean stress (sigma11 + sigma22) / 2 [N/m], shape (n,).
        q: deviator sigma11 - sigma22 [N/m], shape (n,).
        J: volume ratio V / V0 [-], shape (n,).
        volume: macro volume V = V0 J [m^2], shape (n,).
        newton_iterations: ``step`` calls spent on the increment (1 when purely
            strain-controlled), shape (n,), int.
        diagnostics: backend diagnostics of the accepted ``step`` call per increment (e.g.
            DEM ``substeps``, ``n_unconverged``), name -> shape (n,); NaN where absent.
            ``<name>_all_calls`` sums the same diagnostic over every ``step`` call of the
            increment, trial calls of stress control included (the work really spent).
        snapshot_increment: number of completed increments at each snapshot, shape (m,).
        snapshot_stage: stage label of each snapshot, shape (m,), str.
        snapshots: per-cell ``cell_model.observables``, name -> shape (m, n_cells).
        theta_deg: cell-axis orientations [deg], shape (n_cells,).
        weights: fabric weights [-], shape (n_cells,).
        V0: initial macro volume [m^2] (3D: [m^3]).
        parameters: the named parameters of the mesostructure (``Mesostructure.parameters``,
            e.g. ``alpha0_deg`` [deg]), copied without knowing what they are.
        backend: name of the cell model.
        programme: the loading programme that was run.
        final_state: ``cell_model.state_to_arrays`` of the last state (resume, inspection).
        step_seconds: wall time of each programme step [s], shape (n_steps,); not written
            to run files, which stay bit-reproducible.
        eps33, sigma33, sigma23, sigma13: the third normal strain and the stress components of a
            3D run (None in 2D), shape (n,); there p = tr(sigma) / 3 and q = sqrt(3 J2) [Pa],
            sigma12 the 12 shear stress, and theta_deg the angle between each cell axis and axis 1.
        frames: 3D cell frames (n, t1, t2) as columns [-], shape (n_cells, 3, 3); None in 2D.
    """

    stage: np.ndarray
    eps11: np.ndarray
    eps22: np.ndarray
    sigma11: np.ndarray
    sigma22: np.ndarray
    sigma12: np.ndarray
    p: np.ndarray
    q: np.ndarray
    J: np.ndarray
    volume: np.ndarray
    newton_iterations: np.ndarray
    diagnostics: dict[str, np.ndarray]
    snapshot_increment: np.ndarray
    snapshot_stage: np.ndarray
    snapshots: dict[str, np.ndarray]
    theta_deg: np.ndarray
    weights: np.ndarray
    V0: float
    parameters: dict[str, float]
    backend: str
    programme: Programme
    final_state: dict[str, np.ndarray] = field(default_factory=dict)
    step_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))
    eps33: np.ndarray | None = None
    sigma33: np.ndarray | None = None
    sigma23: np.ndarray | None = None
    sigma13: np.ndarray | None = None
    frames: np.ndarray | None = None

    @property
    def n_increments(self) -> int:
        """Number of recorded increments."""
        return int(self.eps11.shape[0])

    @property
    def dim(self) -> int:
        """2 for a plane-strain run, 3 for a triaxial one."""
        return 2 if self.eps33 is None else 3


class _Runner:
    """Mutable state of one run: the material point, accumulated strain, history buffers."""

    def __init__(self, material: HomogenisedMaterial | HomogenisedMaterial3D, n_max: int, stress_rtol: float,
                 max_iterations: int) -> None:
        self.material = material
        self.model = material.model
        self.point = material.init_state()
        self.V0 = float(material.V0[0])
        self.dim = material.dim
        """Controlled normal components: 2 (11, 22) or 3 (11, 22, 33)."""
        n_stress = 3 if self.dim == 2 else 6
        self.unit = "N/m" if self.dim == 2 else "Pa"
        self.eps = np.zeros(self.dim)
        self.sigma = np.zeros(n_stress)
        self.coupling: np.ndarray | None = None
        """Per stress component, d sigma_i / d sigma11 imposed by the current step (None: none)."""
        self.sigma11_start = 0.0
        self.sigma_peak = 0.0
        self.rtol = stress_rtol
        self.max_iterations = max_iterations
        self.last_trial: np.ndarray | None = None
        """The macro increment of the last ``trial`` with a finite increment (None before the first)."""
        self.k = 0
        # 2D: eps11, eps22, sigma11, sigma22, sigma12, J; 3D: eps11..33, sigma (six components), J
        self.rows = np.empty((n_max, self.dim + n_stress + 1))
        self.iterations = np.empty(n_max, dtype=np.int64)
        self.stage_index = np.empty(n_max, dtype=np.int64)
        self.diagnostics: dict[str, np.ndarray] = {}
        self.call_totals: dict[str, float] = {}
        self.snap_k: list[int] = []
        self.snap_stage: list[int] = []
        self.snaps: list[dict[str, np.ndarray]] = []

    @property
    def state(self) -> Any:
        """Cell state of the last accepted increment."""
        return self.point.cells

    def mean(self, sigma: np.ndarray) -> float:
        """p [N/m or Pa] of the stress components ``sigma``."""
        if self.dim == 2:
            return float(mean_stress(sigma[0], sigma[1]))
        return float(mean_stress_3d(sigma[0], sigma[1], sigma[2]))

    def controlled(self, sigma: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """The stresses that stress control sets to its targets: sigma[idx], less the step's coupling to sigma11."""
        if self.coupling is None:
            return sigma[idx]
        return sigma[idx] - self.coupling[idx] * (sigma[0] - self.sigma11_start)

    def controlled_tangent(self, tangent: np.ndarray) -> np.ndarray:
        """d(``controlled``)/d(d_eps) of every stress component row, from the material tangent."""
        if self.coupling is None:
            return tangent
        return tangent - self.coupling[:, None] * tangent[0][None, :]

    # -- one trial -------------------------------------------------------------------------
    def voigt(self, d_eps: np.ndarray) -> np.ndarray:
        """The material's increment (1, n_voigt) of the macro increment ``d_eps``: 2D (11, 22, 12) ->
        (11, 22, 2 x 12), 3D the six tensor components as they are."""
        if self.dim == 2:
            return np.array([[d_eps[0], d_eps[1], 2.0 * d_eps[2]]])
        return np.asarray(d_eps, dtype=np.float64)[None, :]

    def control_diagnosis(self, programme: Sequence[Step], mesostructure: Any) -> str | None:
        """The cell model's one-line diagnosis of a failed stress control (its ``control_diagnosis``,
        e.g. ``homogenization.backends.ann.AnnCell``) at the last trial from the last accepted state;
        None where the model has none or no trial was made."""
        diagnose = getattr(self.model, "control_diagnosis", None)
        if diagnose is None or self.last_trial is None:
            return None
        orient = self.material.orient
        axes = (orient.frames[:, :, 0] if self.dim == 3
                else np.stack([np.cos(orient.theta), np.sin(orient.theta)], axis=1))
        return diagnose(self.point.cells, self.material.localise(self.voigt(self.last_trial)), axes, programme,
                        mesostructure)

    def trial(self, d_eps: np.ndarray, *, with_tangent: bool = False) -> MaterialUpdate:
        """Update the material point by the macro increment ``d_eps`` from the saved state: 2D (11, 22, 12),
        3D the six tensor components (11, 22, 33, 23, 13, 12)."""
        update = self.material.update(self.point, self.voigt(d_eps), with_tangent=with_tangent)
        if np.all(np.isfinite(d_eps)):
            self.last_trial = np.array(d_eps, dtype=np.float64)
        for name, value in update.diagnostics.items():
            self.call_totals[name] = self.call_totals.get(name, 0.0) + float(value)
        return update

    def accept(self, update: MaterialUpdate, d_eps: np.ndarray, iterations: int, stage: int,
               jump: bool | None = None) -> None:
        """Record the trial ``update`` as the next increment; ``jump``: whether stress control
        took the nearer side of a response jump (None where no stress was controlled)."""
        k = self.k
        self.point = update.state
        self.eps += d_eps[:self.dim]
        self.sigma = update.stress[0]
        self.sigma_peak = max(self.sigma_peak, float(np.abs(self.sigma).max()))
        row = self.rows[k]
        row[:self.dim] = self.eps
        row[self.dim:-1] = self.sigma
        row[-1] = update.state.J[0]
        self.iterations[k] = iterations
        self.stage_index[k] = stage
        totals = {f"{name}_all_calls": value for name, value in self.call_totals.items()}
        control = {} if jump is None else {"stress_control_jump": float(jump)}
        for name, value in (*update.diagnostics.items(), *totals.items(), *control.items()):
            if name not in self.diagnostics:
                self.diagnostics[name] = np.full(self.rows.shape[0], np.nan)
            self.diagnostics[name][k] = value
        self.call_totals = {}
        self.k = k + 1

    def snapshot(self, stage: int) -> None:
        if self.snap_k and self.snap_k[-1] == self.k:
            return
        self.snap_k.append(self.k)
        self.snap_stage.append(stage)
        self.snaps.append({name: np.array(v) for name, v in self.model.observables(self.state).items()})

    # -- stress control --------------------------------------------------------------------
    def predict(self, d_eps: np.ndarray, idx: np.ndarray, target: np.ndarray, tangent: np.ndarray | None) -> np.ndarray:
        """First guess of the stress-controlled increments: sigma + D d_eps = target on ``idx``,
        D the last Voigt tangent computed (``d_eps`` unchanged without one)."""
        d_eps = d_eps.copy()
        if tangent is None:
            return d_eps
        tangent = self.controlled_tangent(tangent)
        ctrl = np.setdiff1d(np.arange(self.dim), idx)
        rhs = target - self.controlled(self.sigma, idx) - tangent[np.ix_(idx, ctrl)] @ d_eps[ctrl]
        try:
            d_eps[idx] = np.linalg.solve(tangent[np.ix_(idx, idx)], rhs)
        except np.linalg.LinAlgError:
            pass  # singular last tangent: keep the previous increment as the guess
        return d_eps

    def solve_stress(self, d_eps: np.ndarray, idx: np.ndarray, target: np.ndarray, where: str,
                     tangent: np.ndarray | None) -> tuple[MaterialUpdate, np.ndarray, int, bool, np.ndarray | None]:
        """Find the strain increments of components ``idx`` giving sigma[idx] = ``target``.

        Newton with the material's consistent tangent. The first trial reuses ``tangent`` (the
        last one computed, which also made the predictor) and asks for none: an increment that
        the predictor solves costs one plain step call (computing a DEM cell's tangent costs
        ~10 step calls). Every later trial computes its own. With one controlled component the
        Newton step is safeguarded: once two trials bracket the target (residuals of opposite
        sign), a step that leaves the bracket, or follows a trial that did not halve the
        residual, is replaced by the bracket's midpoint. Where the response jumps across the
        target (a DEM cell that switches between two equilibria, e.g. a grain caught or not,
        within a strain change of ``JUMP_WIDTH`` times the increment), no increment meets
        the tolerance: the bracket end nearer the target is accepted and the increment is
        flagged. ``d_eps`` holds the strain-controlled increments and the initial guess of the
        others. Returns the accepted trial, the solved increment, the ``step`` calls spent, the
        jump flag and the last tangent computed (``tangent`` if none was).
        """
        d_eps = d_eps.copy()
        scale = np.abs(target)
        tol = self.rtol * np.where(scale > 0.0, scale, self.sigma_peak)
        size = float(np.abs(d_eps[:self.dim]).max())
        below = above = None  # (strain, residual, trial, increment) of the last trials under / over the target
        last = np.inf
        calls = 0
        while True:
            update = self.trial(d_eps, with_tangent=calls > 0 or tangent is None)
            calls += 1
            if update.tangent is not None:
                tangent = update.tangent[0]
            r = self.controlled(update.stress[0], idx) - target
            if np.all(np.abs(r) <= tol):
                return update, d_eps, calls, False, tangent
            K = self.controlled_tangent(tangent)[np.ix_(idx, idx)]
            try:
                step = np.linalg.solve(K, r)
            except np.linalg.LinAlgError:
                step = None
            if idx.size == 1:
                x, res = float(d_eps[idx[0]]), float(r[0])
                if res < 0.0:
                    below = (x, res, update, d_eps.copy())
                else:
                    above = (x, res, update, d_eps.copy())
                newton = None if step is None or not np.isfinite(step[0]) else x - float(step[0])
                if below is not None and above is not None:
                    lo, hi = sorted((below[0], above[0]))
                    if hi - lo <= JUMP_WIDTH * max(size, abs(lo), abs(hi)):
                        nearer = min(below, above, key=lambda end: abs(end[1]))
                        return nearer[2], nearer[3], calls, True, tangent
                    if newton is None or not lo < newton < hi or abs(res) > 0.5 * last:
                        newton = 0.5 * (lo + hi)
                last = abs(res)
            if calls >= self.max_iterations:
                raise ControlError(f"{where}: stress control did not converge in {calls} step calls "
                                   f"(residual {float(np.abs(r).max()):.3g} {self.unit}, tolerance {float(tol.min()):.3g} {self.unit})")
            if idx.size == 1 and newton is not None:
                d_eps[idx[0]] = newton
            elif step is None:
                raise ControlError(f"{where}: the material has no stiffness against the controlled stress "
                                   f"(singular tangent)")
            else:
                d_eps[idx] = d_eps[idx] - step

    def solve_stress_secant(self, d_eps: np.ndarray, idx: np.ndarray, target: np.ndarray, where: str,
                            tangent: np.ndarray | None) -> tuple[MaterialUpdate, np.ndarray, int, bool, np.ndarray | None]:
        """``solve_stress`` for several controlled components of a 3D step (lateral stresses of a
        triaxial test), with secant (Broyden) updates of the tangent between trials.

        A cell tangent costs about ten DEM steps, so trials ask for a fresh one only where there is
        none yet or where the last trial did not halve the residual; in between, the rows ``idx``
        of the tangent get Broyden's rank-one update from the previous point of the increment (the
        first from the start of the increment, d_eps = 0, at the saved stress). Same returns as
        ``solve_stress`` (never a jump); the tangent returned carries the updates, for the next
        increment's predictor.
        """
        d_eps = d_eps.copy()
        scale = np.abs(target)
        tol = self.rtol * np.where(scale > 0.0, scale, self.sigma_peak)
        T = None if tangent is None else tangent.copy()
        previous = (np.zeros_like(d_eps), self.controlled(self.sigma, idx))
        fresh = T is None
        last = np.inf
        calls = 0
        while True:
            update = self.trial(d_eps, with_tangent=fresh)
            calls += 1
            g = self.controlled(update.stress[0], idx)
            if update.tangent is not None:
                T = update.tangent[0].copy()
            else:
                dx, dg = d_eps - previous[0], g - previous[1]
                Tc = self.controlled_tangent(T)[idx]
                T[idx] += np.outer(dg - Tc @ dx, dx) / float(dx @ dx)
            r = g - target
            if np.all(np.abs(r) <= tol):
                return update, d_eps, calls, False, T
            if calls >= self.max_iterations:
                raise ControlError(f"{where}: stress control did not converge in {calls} step calls "
                                   f"(residual {float(np.abs(r).max()):.3g} {self.unit}, tolerance "
                                   f"{float(tol.min()):.3g} {self.unit})")
            residual = float(np.abs(r).max())
            fresh = update.tangent is None and residual > 0.5 * last
            last = residual
            previous = (d_eps.copy(), g)
            try:
                step = np.linalg.solve(self.controlled_tangent(T)[np.ix_(idx, idx)], r)
            except np.linalg.LinAlgError:
                raise ControlError(f"{where}: the material has no stiffness against the controlled stress "
                                   f"(singular tangent)") from None
            d_eps[idx] = d_eps[idx] - step

    def land_on_p(self, d_eps: np.ndarray, p_stop: float, p_over: float, where: str):
        """Scale the increment ``d_eps`` by lambda in (0, 1] so that p = ``p_stop`` (Illinois)."""
        tol = self.rtol * p_stop
        lo, f_lo = 0.0, self.mean(self.sigma) - p_stop
        hi, f_hi = 1.0, p_over - p_stop
        side = 0
        for calls in range(1, self.max_iterations + 1):
            lam = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
            d = d_eps * lam
            update = self.trial(d)
            f = self.mean(update.stress[0]) - p_stop
            if abs(f) <= tol:
                return update, d, calls
            if f > 0.0:
                hi, f_hi = lam, f
                if side == 1:
                    f_lo *= 0.5
                side = 1
            else:
                lo, f_lo = lam, f
                if side == -1:
                    f_hi *= 0.5
                side = -1
        raise ControlError(f"{where}: could not land p on {p_stop:g} {self.unit} in {self.max_iterations} step calls")

    # -- one programme step ----------------------------------------------------------------
    def advance(self, bar: tqdm, step: Step) -> None:
        """Count the increment just accepted on ``bar``; a step that stops on p also shows how
        far p is, as a percentage of stop_at_p (its length is unknown, so the bar has no total)."""
        if step.stop_at_p is not None:
            p = self.mean(self.sigma)
            bar.set_postfix_str(f"p = {p / step.stop_at_p:.1%} of {step.stop_at_p:g} {self.unit}", refresh=False)
        bar.update(1)

    def run_step(self, step: Step, stage: int, snapshot_interval: int, bar: tqdm) -> None:
        """Run the increments of ``step``; ``bar`` counts them (and p as a percentage of stop_at_p where the step stops on p)."""
        n = step.n_increments
        if step.dim != self.dim:
            raise ValueError(f"step {step.label!r} controls {step.dim} components; the cells are {self.dim}D")
        mask = np.array(step.stress_mask)
        idx = np.flatnonzero(mask)
        d_eps = np.zeros(3 if self.dim == 2 else 6)
        d_eps[:self.dim] = np.where(mask, 0.0, np.asarray(step.target) / n)
        sigma_start = self.sigma[:self.dim].copy()
        target_end = np.asarray(step.target)
        self.sigma11_start = float(self.sigma[0])
        self.coupling = None
        if step.coupling is not None:
            self.coupling = np.zeros(self.sigma.shape[0])
            self.coupling[:self.dim] = step.coupling
        if step.stop_at_p is not None and self.mean(self.sigma) >= step.stop_at_p:
            raise ControlError(f"step {step.label!r} starts at p = {self.mean(self.sigma):.6g} {self.unit}, "
                               f"already at or above stop_at_p = {step.stop_at_p:g} {self.unit}")
        tangent = None
        for i in range(n):
            if idx.size:
                target = sigma_start[idx] + (target_end[idx] - sigma_start[idx]) * ((i + 1) / n)
                where = f"step {step.label!r}, increment {i + 1}"
                d_eps = self.predict(d_eps, idx, target, tangent)
                solve = self.solve_stress_secant if self.dim == 3 and idx.size > 1 else self.solve_stress
                update, d_eps, calls, jump, tangent = solve(d_eps, idx, target, where, tangent)
            else:
                update = self.trial(d_eps)
                calls, jump = 1, None
                if step.stop_at_p is not None:
                    p_new = self.mean(update.stress[0])
                    if p_new >= step.stop_at_p:
                        if p_new - step.stop_at_p > self.rtol * step.stop_at_p:
                            where = f"step {step.label!r}, increment {i + 1}"
                            update, d, extra = self.land_on_p(d_eps, step.stop_at_p, p_new, where)
                            calls += extra
                        else:
                            d = d_eps
                        self.accept(update, d, calls, stage)
                        self.advance(bar, step)
                        return
            self.accept(update, d_eps, calls, stage, jump)
            self.advance(bar, step)
            if snapshot_interval and self.k % snapshot_interval == 0:
                self.snapshot(stage)
        if step.stop_at_p is not None:
            raise ControlError(f"step {step.label!r} ended at p = {self.mean(self.sigma):.6g} {self.unit} "
                               f"before reaching {step.stop_at_p:g} {self.unit}; allow more strain")


def _orientations_3d(mesostructure: Mesostructure, fabric_anisotropy: float, order: int, n_spins: int,
                     spin_period_deg: float | None, staggered: bool) -> orientation3d.Orientations3D:
    """The orientation set of a 3D run (``run``); ValueError for an anisotropic fabric."""
    if fabric_anisotropy:
        raise ValueError("an anisotropic fabric is not available in 3D yet (fabric_anisotropy must be 0)")
    period = mesostructure.spin_period_deg() if spin_period_deg is None else spin_period_deg
    return orientation3d.orientations_3d(order, n_spins, spin_period_deg=period, staggered=staggered,
                                         kinematics=orientation3d.cell_kinematics(mesostructure))


def _run_stages(runner: _Runner, programme: Programme, mesostructure: Any, snapshot_interval: int,
                progress: bool) -> np.ndarray:
    """Run every step of ``programme`` in turn; returns the wall time of each [s]. A ``ControlError``
    leaves with the cell model's diagnosis appended (``_Runner.control_diagnosis``), where it has one."""
    step_seconds = np.zeros(len(programme))
    for stage, step in enumerate(programme):
        start = time.perf_counter()
        # a step that stops on p has no known length: the bar counts increments without a total
        total = None if step.stop_at_p is not None else step.n_increments
        with progress_bar(total=total, desc=step.label, unit="incr", disable=not progress, leave=False) as bar:
            try:
                runner.run_step(step, stage, snapshot_interval, bar)
            except ControlError as exc:
                diagnosis = runner.control_diagnosis(programme, mesostructure)
                if diagnosis is None:
                    raise
                raise ControlError(f"{exc}; {diagnosis}") from None
        runner.snapshot(stage)
        step_seconds[stage] = time.perf_counter() - start
    return step_seconds


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
    progress: bool = True,
    lebedev_order: int = LEBEDEV_ORDER,
    n_spins: int = N_SPINS,
    spin_period_deg: float | None = None,
    staggered_spins: bool = True,
) -> Record:
    """Run ``programme`` on ``n_orientations`` cells of ``cell_model`` and record the history.

    Args:
        cell_model: any ``CellModel`` backend.
        programme: loading steps, run in order (see ``homogenization.loading``).
        mesostructure: the cell every orientation starts from (e.g.
            ``warp_hcell.mesostructures.hcell.h_cell(alpha0_deg, radius)``, a builder spec or a file).
        n_orientations: number N of cell orientations theta_k = k pi / N.
        fabric_anisotropy: a_f in [0, 1) of the weights w(theta) (0 = isotropic fabric).
        fabric_direction_deg: preferred fabric direction b_f [deg].
        snapshot_interval: also store per-cell observables every this many increments
            (0: only at the end of each stage).
        stress_rtol: relative tolerance on stress-controlled components [-].
        max_newton_iterations: ``step`` calls allowed per stress-controlled increment.
        progress: show a progress bar per stage (``warp_hcell.core.cli.progress_bar``: off under -q).
        lebedev_order, n_spins, spin_period_deg: the orientations of a 3D programme (steps of three
            components, cells of dimension 3; ``orientation3d.orientations_3d``), which ignores
            ``n_orientations`` and takes an isotropic fabric only; ``spin_period_deg`` None: the
            cell's own (``Mesostructure.spin_period_deg``); ``staggered_spins`` False: every axis
            has the same spins (``orientation3d.orientations_3d``, which says what that keeps).

    Returns:
        The ``Record`` of the run.

    Raises:
        ValueError: invalid programme or options (one line).
        ControlError: a stress-controlled increment could not be solved.
    """
    programme = validate(programme)
    if snapshot_interval < 0:
        raise ValueError(f"snapshot_interval = {snapshot_interval} must be >= 0")
    dim = dimension(programme)
    meso_dim = getattr(mesostructure, "dim", 2)
    if meso_dim != dim:
        raise ValueError(f"the programme controls {dim} components but mesostructure {mesostructure.name!r} is a "
                         f"{meso_dim}D cell")
    if dim == 2:
        orient = orient_mod.orientations(n_orientations, anisotropy=fabric_anisotropy, direction_deg=fabric_direction_deg)
        material = HomogenisedMaterial(cell_model, orient, mesostructure, 1)
    else:
        orient = _orientations_3d(mesostructure, fabric_anisotropy, lebedev_order, n_spins, spin_period_deg,
                                  staggered_spins)
        material = HomogenisedMaterial3D(cell_model, orient, mesostructure, 1)
    runner = _Runner(material, sum(s.n_increments for s in programme), stress_rtol, max_newton_iterations)
    V0 = runner.V0
    labels = [s.label for s in programme]
    step_seconds = _run_stages(runner, programme, mesostructure, snapshot_interval, progress)

    k = runner.k
    jumps = int(np.nansum(runner.diagnostics.get("stress_control_jump", np.zeros(0))[:k]))
    if jumps:
        warnings.warn(f"stress control met a jump of the response across its target at {jumps} increment(s): the "
                      f"side nearer the target was accepted (diagnostics 'stress_control_jump')", RuntimeWarning,
                      stacklevel=2)
    rows = runner.rows[:k]
    snap_names = runner.snaps[0].keys() if runner.snaps else ()
    label_array = np.array(labels)
    if dim == 2:
        sigma11, sigma22 = rows[:, 2].copy(), rows[:, 3].copy()
        sigma12 = rows[:, 4].copy()
        p, q = mean_stress(sigma11, sigma22), deviator(sigma11, sigma22)
        theta_deg, spatial = np.degrees(orient.theta), {}
    else:
        sigma11, sigma22, sigma33, sigma23, sigma13, sigma12 = (rows[:, 3 + m].copy() for m in range(6))
        p = mean_stress_3d(sigma11, sigma22, sigma33)
        q = deviator_3d(sigma11, sigma22, sigma33, sigma23, sigma13, sigma12)
        theta_deg = np.degrees(np.arccos(np.clip(np.abs(orient.frames[:, 0, 0]), 0.0, 1.0)))
        spatial = dict(eps33=rows[:, 2].copy(), sigma33=sigma33, sigma23=sigma23, sigma13=sigma13,
                       frames=np.array(orient.frames))
    return Record(
        stage=label_array[runner.stage_index[:k]],
        eps11=rows[:, 0].copy(),
        eps22=rows[:, 1].copy(),
        sigma11=sigma11,
        sigma22=sigma22,
        sigma12=sigma12,
        p=p,
        q=q,
        J=rows[:, -1].copy(),
        volume=V0 * rows[:, -1],
        newton_iterations=runner.iterations[:k].copy(),
        diagnostics={name: v[:k].copy() for name, v in runner.diagnostics.items()},
        snapshot_increment=np.array(runner.snap_k, dtype=np.int64),
        snapshot_stage=label_array[np.array(runner.snap_stage, dtype=np.int64)],
        snapshots={name: np.stack([s[name] for s in runner.snaps]) for name in snap_names},
        theta_deg=theta_deg,
        weights=np.array(orient.weights),
        V0=V0,
        parameters=dict(mesostructure.parameters),
        backend=str(getattr(cell_model, "name", type(cell_model).__name__)),
        programme=programme,
        final_state={name: np.array(v) for name, v in cell_model.state_to_arrays(runner.state).items()},
        step_seconds=step_seconds,
        **spatial,
    )
