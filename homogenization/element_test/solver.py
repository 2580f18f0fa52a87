"""The stress-control solver of the element test, batched over material points (and so over parameter sets).

``StressControl(points, policy)`` solves, for n material points at once, the strain increments of the
stress-controlled components of an increment (``solve``: Newton on the material's consistent
tangent) and the scale of a strain increment that lands p on a stop value (``land_on_p``: Illinois).
Every trial is one batched ``step`` from the saved state (steps are pure); a point is accepted as
soon as it meets its tolerance, the others iterate on, so a point's result does not depend on its
batch. Convergence: every controlled stress within ``rtol`` times its ``|target|`` (times the largest
``|sigma|`` the point has carried where the target is zero); a landing within ``rtol`` times the stop.

``Policy`` says how the iterations spend step calls and what a failure does:

- ``STRICT`` (a recorded run, ``homogenization.element_test.driver``): the first trial of an increment reuses the
  last tangent (a DEM tangent costs ~10 step calls), later ones compute their own; with several
  controlled components of a 3D step, trials between fresh tangents take Broyden's rank-one update
  (a fresh one only where the last trial did not halve the residual); with one controlled component
  the Newton step is safeguarded by bisection once two trials bracket the target, and where the
  response jumps across the target (within ``JUMP_WIDTH`` of the increment) the nearer side is
  accepted and flagged; with several controlled components, a point still unconverged after
  ``max_iterations`` trials, whose worst controlled stress jumps across its target within
  ``JUMP_WIDTH`` of the increment next to its trial nearest the target (found by bisection,
  ``_several_jump``), takes that trial, flagged the same way; linear systems by LAPACK; a point that does not converge raises
  ``ControlError``.
- ``POPULATION`` (a calibration's parameter sets, ``homogenization.calibration.forward``): a fresh
  tangent every trial, systems of one or two components by Cramer's rule (a singular tangent gives a
  non-finite step instead of an exception), bisection safeguards (one component: ``bracket``; several:
  ``segment``), their jumps taken at ``POPULATION_JUMP_WIDTH`` (plain Newton cycles between the two sides
  of a jump until its trials are spent), and a point that does not converge in ``max_iterations``
  trials, or whose residual is not finite, takes its last iterate and is counted (``fallback``).

``StressControl.jumps`` counts, per point, the increments that took the nearer side of a jump.

Increments are Voigt rows (n, n_voigt) [-]; stresses [N/m] (2D) or [Pa] (3D); compression positive.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from homogenization.element_test.points import MaterialPoints
from homogenization.element_test.plan import Plan
from warp_hcell.core.parameters import LoadingDefaults

JUMP_WIDTH = 1e-6
"""Bracket width, as a fraction of the increment, below which stress control takes the
response for discontinuous at the target (``StressControl.solve``) [-]: the residual still
above the tolerance there means a slope ~1e6 times the material's own (about 20 bisections)."""
POPULATION_NEWTON_FIRST = 6
"""``Policy.newton_first`` of the ``POPULATION`` policy: Newton's trials before its safeguards engage."""
POPULATION_JUMP_WIDTH = 1e-3
"""``JUMP_WIDTH`` of the ``POPULATION`` policy [-]: the jump's strain located to 1e-3 of the increment (about
10 bisections), its stress then off the located jump's by about 1e-3 of an increment's stress change."""


class ControlError(RuntimeError):
    """A stress-controlled increment did not converge (e.g. the material cannot carry the target)."""


@dataclass(frozen=True)
class Policy:
    """How stress control iterates (module docstring).

    Attributes:
        rtol: relative tolerance of controlled stresses and of a landing on p [-].
        max_iterations: trials allowed per increment (per landing).
        strict: raise ``ControlError`` where a point does not converge; else take its last iterate and count it.
        reuse_tangent: the first trial of an increment reuses the last tangent instead of computing one.
        secant: Broyden updates between fresh tangents where a 3D step controls several components.
        bracket: bisection safeguard and jump detection where one component is controlled.
        cramer: linear systems by Cramer's rule (non-finite where singular) instead of LAPACK.
        jump_width: bracket width below which a safeguard takes the response for discontinuous, a
            fraction of the increment [-].
        segment: bisection safeguard and jump detection where several components are controlled (``_Segment``).
        newton_first: trials of plain Newton before a safeguard may replace its step.
    """

    rtol: float = LoadingDefaults.stress_rtol
    max_iterations: int = LoadingDefaults.max_newton_iterations
    strict: bool = True
    reuse_tangent: bool = True
    secant: bool = True
    bracket: bool = True
    cramer: bool = False
    jump_width: float = JUMP_WIDTH
    segment: bool = False
    newton_first: int = 0


STRICT = Policy()
"""The policy of a recorded run (``homogenization.element_test.driver.run``)."""
POPULATION = Policy(strict=False, reuse_tangent=False, secant=False, bracket=True, cramer=True,
                    jump_width=POPULATION_JUMP_WIDTH, segment=True, newton_first=POPULATION_NEWTON_FIRST)
"""The policy of a calibration's population of parameter sets."""


def cramer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x of a x = b per point, a (n, k, k), b (n, k), k = 1 or 2, by Cramer's rule: a singular a gives inf or
    NaN rather than an exception."""
    if a.shape[1] == 1:
        return b / a[:, :, 0]
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    return np.stack([b[:, 0] * a[:, 1, 1] - b[:, 1] * a[:, 0, 1], a[:, 0, 0] * b[:, 1] - a[:, 1, 0] * b[:, 0]],
                    axis=1) / det[:, None]


@dataclass
class Solved:
    """What ``StressControl.solve`` leaves besides the accepted points.

    Attributes:
        increment: each point's accepted increment (n, n_voigt) [-], the next increment's first guess.
        calls: trials (batched step calls) spent.
        jump: per point, whether the nearer side of a response jump was accepted, shape (n,).
        fallback: per point, 1 where the last iterate was taken unconverged (``POPULATION``), shape (n,).
        tangent: the last tangent of each point (n, m, n_voigt), for the next increment's predictor.
    """

    increment: np.ndarray
    calls: int
    jump: np.ndarray
    fallback: np.ndarray
    tangent: np.ndarray | None


class StressControl:
    """The stress-control solver of ``points`` under ``policy`` (module docstring)."""

    def __init__(self, points: MaterialPoints, policy: Policy = STRICT) -> None:
        self.points = points
        self.policy = policy
        self.jumps = np.zeros(points.n, dtype=np.int64)
        """Per point, the increments whose solution took the nearer side of a response jump (``Solved.jump``)."""

    def _linear(self, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """x of a x = b per point (a (n, k, k), b (n, k)); None where LAPACK finds a singular a."""
        if self.policy.cramer:
            return cramer(a, b)
        try:
            return np.linalg.solve(a, b[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return None

    def predict(self, d: np.ndarray, plan: Plan, target: np.ndarray, tangent: np.ndarray | None) -> np.ndarray:
        """First guess of the stress-controlled increments: sigma + D d = target on ``plan.idx``, D the last
        tangent (``d`` unchanged without one, or where D is singular)."""
        d = d.copy()
        if tangent is None:
            return d
        idx = plan.idx
        T = plan.controlled_tangent(tangent)
        ctrl = np.setdiff1d(np.arange(self.points.dim), idx)
        known = np.einsum("pkc,pc->pk", T[:, idx][:, :, ctrl], d[:, ctrl])
        solved = self._linear(T[:, idx][:, :, idx], target - plan.controlled(self.points.stress) - known)
        if solved is not None:
            d[:, idx] = solved
        return d

    def land_on_p(self, d: np.ndarray, crossing: np.ndarray, over, p_stop: float,
                  where: object) -> tuple[int, np.ndarray]:
        """Shorten the increment ``d`` of the points of ``crossing``, whose trial ``over`` went past
        ``p_stop``, by lambda in (0, 1] so that p = ``p_stop`` (Illinois), and accept them.

        Returns the trials spent and, per point, 1 where the tolerance was not met (``POPULATION``: the last
        iterate is taken)."""
        points, rtol = self.points, self.policy.rtol
        p_over = points.mean(over.stress)
        lo, f_lo = np.zeros(points.n), points.mean(points.stress) - p_stop
        hi, f_hi = np.ones(points.n), p_over - p_stop
        side = np.zeros(points.n)
        todo = crossing & (p_over - p_stop > rtol * p_stop)
        points.accept(over, crossing & ~todo)
        calls = 0
        for _ in range(self.policy.max_iterations):
            if not todo.any():
                return calls, np.zeros(points.n, dtype=np.int64)
            lam = np.where(todo, (lo * f_hi - hi * f_lo) / np.where(todo, f_hi - f_lo, 1.0), 1.0)
            update = points.trial(d * lam[:, None])
            calls += 1
            f = points.mean(update.stress) - p_stop
            done = todo & (np.abs(f) <= rtol * p_stop)
            points.accept(update, done)
            above = todo & ~done & (f > 0.0)
            below = todo & ~done & (f <= 0.0)
            f_lo = np.where(above & (side == 1), 0.5 * f_lo, f_lo)
            f_hi = np.where(below & (side == -1), 0.5 * f_hi, f_hi)
            hi, f_hi = np.where(above, lam, hi), np.where(above, f, f_hi)
            lo, f_lo = np.where(below, lam, lo), np.where(below, f, f_lo)
            side = np.where(above, 1.0, np.where(below, -1.0, side))
            todo &= ~done
        if todo.any() and self.policy.strict:
            raise ControlError(f"{where}: could not land p on {p_stop:g} {points.unit} in "
                               f"{self.policy.max_iterations} step calls")
        points.accept(update, todo)
        return calls, todo.astype(np.int64)

    def solve(self, d: np.ndarray, plan: Plan, target: np.ndarray, tangent: np.ndarray | None,
              where: object) -> Solved:
        """Find the increments of the components ``plan.idx`` that give the controlled stresses ``target``
        (n, k) at every point, starting from the guess ``d`` (n, n_voigt; its strain-controlled components
        are the increment's), and accept each point's solution (module docstring); the jumps taken are
        counted in ``jumps``. ``tangent``: the last tangent of each point (None: none yet); ``where``: names
        the increment in an error.

        Raises:
            ControlError: (``STRICT``) a point did not converge, or its tangent is singular.
        """
        solved = self._solve(d, plan, target, tangent, where)
        self.jumps += solved.jump
        return solved

    def _solve(self, d: np.ndarray, plan: Plan, target: np.ndarray, tangent: np.ndarray | None,
               where: object) -> Solved:
        """``solve`` without the count."""
        points, policy, idx = self.points, self.policy, plan.idx
        n = points.n
        d = d.copy()
        scale = np.abs(target)
        tol = policy.rtol * np.where(scale > 0.0, scale, points.peak[:, None])
        secant = policy.secant and points.dim == 3 and idx.size > 1
        bracket = (_Bracket(n, d, points.dim, int(idx[0]), policy.jump_width, policy.newton_first)
                   if policy.bracket and idx.size == 1 else None)
        segment = (_Segment(n, d, points.dim, idx, policy.jump_width, policy.newton_first)
                   if policy.segment and idx.size > 1 else None)
        T = None if tangent is None else tangent.copy()
        fresh = T is None or not policy.reuse_tangent
        previous = (np.zeros_like(d), plan.controlled(points.stress))
        todo = np.ones(n, dtype=bool)
        jump, fallback = np.zeros(n, dtype=bool), np.zeros(n, dtype=np.int64)
        last = np.full(n, np.inf)
        calls = 0
        trials: list = []
        while True:
            update = points.trial(d, with_tangent=fresh)
            calls += 1
            g = plan.controlled(update.stress)
            if secant and policy.strict:
                trials.append((update, d.copy(), g))
            if update.tangent is not None:
                T = update.tangent.copy() if T is None else np.where(todo[:, None, None], update.tangent, T)
            elif secant:
                _broyden(T, plan, d - previous[0], g - previous[1], todo)
            r = g - target
            done = todo & np.all(np.abs(r) <= tol, axis=1)
            lost = todo & ~np.all(np.isfinite(r), axis=1) if not policy.strict else np.zeros(n, dtype=bool)
            points.accept(update, done | lost)
            fallback += lost
            todo &= ~(done | lost)
            if not todo.any():
                return Solved(d, calls, jump, fallback, T)
            step = self._linear(np.where(todo[:, None, None], plan.controlled_tangent(T)[:, idx][:, :, idx],
                                         np.eye(idx.size)), r)
            newton = None
            if bracket is not None:
                newton = bracket.update(d, r, step, update, todo, last, calls)
                _take_jumps(bracket, points, d, jump, todo)
                if not todo.any():
                    return Solved(d, calls, jump, fallback, T)
            bisected = None
            if segment is not None:
                bisected = segment.update(d, r, tol, todo, last, update)
                _take_jumps(segment, points, d, jump, todo)
                if not todo.any():
                    return Solved(d, calls, jump, fallback, T)
            residual = np.abs(r).max(axis=1)
            if calls >= policy.max_iterations:
                if trials:
                    jumped, spent = _several_jump(points, plan, trials, target, tol, todo,
                                                  np.abs(d[:, :points.dim]).max(axis=1))
                    calls += spent
                    if (jumped == todo).all():
                        for trial, trial_d, mask in _nearest_trials(trials, target, tol, todo):
                            points.accept(trial, mask)
                            d[mask] = trial_d[mask]
                        return Solved(d, calls, jump | todo, fallback, T)
                if policy.strict:
                    raise ControlError(f"{where}: stress control did not converge in {calls} step calls (residual "
                                       f"{float(residual[todo].max()):.3g} {points.unit}, tolerance "
                                       f"{float(tol[todo].min()):.3g} {points.unit})")
                points.accept(update, todo)
                return Solved(d, calls, jump, fallback + todo, T)
            fresh = (update.tangent is None and bool(np.any(residual[todo] > 0.5 * last[todo]))) if secant else True
            last = np.where(todo, residual, last)
            previous = (d.copy(), g)
            if newton is not None and np.all(np.isfinite(newton[todo])):
                d[:, idx[0]] = np.where(todo, newton, d[:, idx[0]])
            elif step is None:
                raise ControlError(f"{where}: the material has no stiffness against the controlled stress "
                                   f"(singular tangent)")
            else:
                d[:, idx] = np.where(todo[:, None], d[:, idx] - step, d[:, idx])
            if bisected is not None:
                mid = todo & np.all(np.isfinite(bisected), axis=1)
                d[:, idx] = np.where(mid[:, None], bisected, d[:, idx])


class _Segment:
    """The bisection safeguard of several controlled components, per point (``Policy.segment``): where a trial
    (from the ``newton_first``-th on) leaves the worst controlled stress c on the other side of its target
    than the trial before, without halving the largest residual, the segment between the two trials is
    bisected, keeping the half across which c's residual changes sign. A midpoint within c's tolerance
    hands the point back to Newton; a segment narrower than ``width`` of the increment with c's residual
    above its tolerance at both ends is a jump of the response (``jumped``), whose end nearer the target
    is taken."""

    def __init__(self, n: int, d: np.ndarray, dim: int, idx: np.ndarray, width: float, newton_first: int = 0) -> None:
        self.idx, self.width, self.newton_first = idx, width, newton_first
        self.size = np.abs(d[:, :dim]).max(axis=1)
        self.active = np.zeros(n, dtype=bool)
        """Per point, whether its segment is being bisected."""
        self.c = np.zeros(n, dtype=np.int64)
        self.ends = np.zeros((2, n, idx.size))
        """Controlled increments of the two ends, per point."""
        self.res = np.zeros((2, n))
        """c's residual at the two ends."""
        self.trial = np.zeros((2, n), dtype=np.int64)
        self.trials: list = []
        self.previous: tuple[np.ndarray, np.ndarray] | None = None
        self.jumped = np.zeros(n, dtype=bool)

    def update(self, d: np.ndarray, r: np.ndarray, tol: np.ndarray, todo: np.ndarray, last: np.ndarray,
               update) -> np.ndarray:
        """Record the trial (increments ``d``, residuals ``r`` (n, k), tolerances ``tol`` (n, k); ``last``: each
        point's largest residual of the trial before) and return the next controlled increments (n, k): the
        segment's midpoint where it is bisected, NaN elsewhere (Newton's step); sets ``jumped``."""
        rows, x, t = np.arange(d.shape[0]), d[:, self.idx].copy(), len(self.trials)
        self.trials.append((update, d.copy()))
        rc = r[rows, self.c]
        inside = todo & self.active & (np.abs(rc) <= tol[rows, self.c])
        self.active &= ~inside  # c met: back to Newton for the other components
        for side in (0, 1):
            mark = todo & self.active & (np.sign(rc) == np.sign(self.res[side]))
            self.ends[side][mark], self.res[side][mark], self.trial[side][mark] = x[mark], rc[mark], t
        if self.previous is not None and t + 1 >= self.newton_first:
            x_prev, r_prev = self.previous
            c = np.argmax(np.abs(r) / tol, axis=1)
            flips = np.sign(r[rows, c]) == -np.sign(r_prev[rows, c])
            start = todo & ~self.active & ~inside & flips & (np.abs(r).max(axis=1) > 0.5 * last)
            self.c[start] = c[start]
            for side, (x_end, r_end, t_end) in enumerate(((x_prev, r_prev, t - 1), (x, r, t))):
                self.ends[side][start], self.res[side][start] = x_end[start], r_end[start, c[start]]
                self.trial[side][start] = t_end
            self.active |= start
        self.previous = (x, r.copy())
        narrow = np.abs(self.ends[1] - self.ends[0]).max(axis=1) <= self.width * self.size
        above = (np.abs(self.res) > tol[rows, self.c]).all(axis=0)
        self.jumped = todo & self.active & narrow & above
        self.active &= ~(narrow & ~above)
        mid = todo & self.active & ~narrow
        out = np.full_like(x, np.nan)
        out[mid] = 0.5 * (self.ends[0][mid] + self.ends[1][mid])
        return out

    def nearer_trials(self, jumped: np.ndarray):
        """(trial update, its increments, mask) of the end nearer the target (in c) of every point of ``jumped``."""
        chosen = np.where(np.abs(self.res[0]) <= np.abs(self.res[1]), self.trial[0], self.trial[1])
        for t in np.unique(chosen[jumped]):
            yield (*self.trials[t], jumped & (chosen == t))


def _take_jumps(tracker: "_Bracket | _Segment", points: MaterialPoints, d: np.ndarray, jump: np.ndarray,
                todo: np.ndarray) -> None:
    """Accept the nearer side of every point whose jump ``tracker`` has located: its state and its
    controlled strains ``d`` (n, k) are set in place, ``jump`` (n,) marks it and ``todo`` (n,) drops it."""
    jumped = tracker.jumped
    for trial, trial_d, mask in tracker.nearer_trials(jumped):
        points.accept(trial, mask)
        d[mask] = trial_d[mask]
    jump |= jumped
    todo &= ~jumped


def _broyden(T: np.ndarray, plan: Plan, dx: np.ndarray, dg: np.ndarray, todo: np.ndarray) -> None:
    """Broyden's rank-one update, in place, of the rows ``plan.idx`` of the tangents ``T`` of the points of
    ``todo``, from a step ``dx`` (n, n_voigt) that changed the controlled stresses by ``dg`` (n, k)."""
    idx = plan.idx
    Tc = plan.controlled_tangent(T)[:, idx]
    for p in np.flatnonzero(todo):
        T[p, idx] += np.outer(dg[p] - Tc[p] @ dx[p], dx[p]) / float(dx[p] @ dx[p])


def _several_jump(points: MaterialPoints, plan: Plan, trials: list, target: np.ndarray, tol: np.ndarray,
                  todo: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, int]:
    """Per point of ``todo`` (n,), whether the response jumps across the target next to its trial nearest the
    target a: in a's worst component c (largest abs residual over the tolerance), b is the trial nearest a
    whose residual in c has the other sign; the segment [a, b] is bisected, keeping the half across which
    c's residual changes sign, to ``JUMP_WIDTH`` of the increment, and c's residual is still above the
    tolerance at both ends (the one-component bracket's test, on the segment). ``trials``: (update, increments, controlled stresses) of every trial; the bisection's trials
    are appended; ``size``: largest abs strain increment of each point [-]. Returns the mask and the step
    calls spent."""
    rows = np.arange(todo.size)
    d_all = np.stack([t[1] for t in trials])
    r_all = np.stack([t[2] for t in trials]) - target
    a = np.argmin((np.abs(r_all) / tol).max(axis=2), axis=0)
    d_a, r_a = d_all[a, rows], r_all[a, rows]
    c = np.argmax(np.abs(r_a) / tol, axis=1)
    distance = np.abs(d_all - d_a).max(axis=2)
    across = np.sign(r_all[:, rows, c]) == -np.sign(r_a[rows, c])
    b = np.argmin(np.where(across, distance, np.inf), axis=0)
    found = todo & across.any(axis=0)
    d_b, r_b = d_all[b, rows], r_all[b, rows]
    calls = 0
    while True:
        wide = np.abs(d_b - d_a).max(axis=1) > JUMP_WIDTH * size
        split = found & wide
        if not split.any():
            above = (np.abs(r_a[rows, c]) > tol[rows, c]) & (np.abs(r_b[rows, c]) > tol[rows, c])
            return found & above, calls
        d_m = np.where(split[:, None], 0.5 * (d_a + d_b), d_a)
        update = points.trial(d_m)
        calls += 1
        r_m = plan.controlled(update.stress) - target
        trials.append((update, d_m, np.where(split[:, None], r_m + target, np.inf)))
        same_as_a = split & (np.sign(r_m[rows, c]) == np.sign(r_a[rows, c]))
        to_b = split & ~same_as_a
        d_a, r_a = np.where(same_as_a[:, None], d_m, d_a), np.where(same_as_a[:, None], r_m, r_a)
        d_b, r_b = np.where(to_b[:, None], d_m, d_b), np.where(to_b[:, None], r_m, r_b)


def _nearest_trials(trials: list, target: np.ndarray, tol: np.ndarray, todo: np.ndarray):
    """(trial update, its increments, mask) of the trial nearest the target (largest abs residual over the
    tolerance) of every point of ``todo``."""
    ratio = np.stack([(np.abs(g - target) / tol).max(axis=1) for _, _, g in trials])
    chosen = np.argmin(ratio, axis=0)
    for t in np.unique(chosen[todo]):
        yield trials[t][0], trials[t][1], todo & (chosen == t)


class _Bracket:
    """The bisection safeguard of one controlled component, per point (``StressControl.solve``): the last
    trials below and above the target, and the trials themselves, for accepting the nearer side of a jump."""

    def __init__(self, n: int, d: np.ndarray, dim: int, column: int, width: float = JUMP_WIDTH,
                 newton_first: int = 0) -> None:
        self.column = column
        """The controlled component."""
        self.newton_first = newton_first
        """Trials before a midpoint may replace Newton's step."""
        self.width = width
        """Bracket width below which the response is taken for discontinuous, a fraction of the increment [-]."""
        self.size = np.abs(d[:, :dim]).max(axis=1)
        self.x = np.full((2, n), np.nan)
        """Increments of the last trial below (row 0) and above (row 1) the target, per point."""
        self.res = np.full((2, n), np.nan)
        self.trial = np.full((2, n), -1, dtype=np.int64)
        self.trials: list = []
        self.jumped = np.zeros(n, dtype=bool)

    def update(self, d: np.ndarray, r: np.ndarray, step: np.ndarray | None, update, todo: np.ndarray,
               last: np.ndarray, calls: int) -> np.ndarray:
        """Record the trial (increments ``d``, residuals ``r`` (n, 1)) and return the next increment of the
        component per point: Newton's, or the bracket's midpoint where Newton leaves the bracket or the
        last trial did not halve the residual; sets ``jumped`` where the bracket is narrower than ``width``."""
        x, res = d[:, self.column], r[:, 0]
        self.trials.append((update, d.copy()))
        side = np.where(res < 0.0, 0, 1)
        for s in (0, 1):
            mark = todo & (side == s)
            self.x[s] = np.where(mark, x, self.x[s])
            self.res[s] = np.where(mark, res, self.res[s])
            self.trial[s] = np.where(mark, calls - 1, self.trial[s])
        newton = np.full(x.shape, np.nan) if step is None else x - step[:, 0]
        newton = np.where(np.isfinite(newton), newton, np.nan)
        both = todo & (self.trial >= 0).all(axis=0)
        lo, hi = np.minimum(self.x[0], self.x[1]), np.maximum(self.x[0], self.x[1])
        width = self.width * np.maximum(np.maximum(self.size, np.abs(lo)), np.abs(hi))
        self.jumped = both & (hi - lo <= width)
        outside = np.isnan(newton) | ~((lo < newton) & (newton < hi)) | (np.abs(res) > 0.5 * last)
        return np.where(both & ~self.jumped & outside & (calls >= self.newton_first), 0.5 * (lo + hi), newton)

    def nearer_trials(self, jumped: np.ndarray):
        """(trial update, its increments, mask) of the side nearer the target of every point of ``jumped``."""
        side = np.where(np.abs(self.res[0]) <= np.abs(self.res[1]), 0, 1)
        chosen = np.where(side == 0, self.trial[0], self.trial[1])
        for t in np.unique(chosen[jumped]):
            yield (*self.trials[t], jumped & (chosen == t))
