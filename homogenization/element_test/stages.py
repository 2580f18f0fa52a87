"""Run the stages of a loading programme on material points from their present state:
``run_stages(solver, stages, history)``.

Each stage (``plan.Plan``) advances every point by its increments: strain-controlled components
as given, stress-controlled ones solved by the stress-control solver (``solver.StressControl``), and a
stage that stops on p lands each point on the stop (its crossing increment shortened) and leaves it
there while the others go on. The points start wherever they are, so a test continues after an erosion
or a restart without being glued from two runs. ``History`` records every increment.

Stresses [N/m] (2D) or [Pa] (3D), strains [-], compression positive.
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from typing import Callable, ContextManager, Iterable, Mapping

import numpy as np

from homogenization.element_test.points import MaterialPoints
from homogenization.element_test.plan import Plan
from homogenization.element_test.record import History
from homogenization.element_test.solver import ControlError, StressControl
from homogenization.element_test.programme import Step

Progress = Callable[[Plan, MaterialPoints], None]
"""Called after every recorded increment of a stage (e.g. a progress bar's update)."""
StageProgress = Callable[[Plan], ContextManager[Progress]]
"""``progress(plan)`` -> a context, open while the stage runs, that gives the stage's ``Progress`` callback."""


def run_stage(solver: StressControl, plan: Plan, history: History, stage: int, *, snapshot_interval: int = 0,
              progress: Progress | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run the increments of ``plan`` on ``solver.points``; returns per point the increments where an
    unconverged iterate was taken, and whether a stage that stops on p ended before reaching it (both under
    a non-strict policy only; a strict one raises).

    Raises:
        homogenization.element_test.solver.ControlError: (strict policy) a stress-controlled increment
            or landing did not converge, or a stage that stops on p starts at or above it or ends before
            reaching it.
    """
    points = solver.points
    fallback = np.zeros(points.n, dtype=np.int64)
    if plan.stop_at_p is not None and np.any(points.mean(points.stress) >= plan.stop_at_p):
        p = float(points.mean(points.stress).max())
        raise ControlError(f"step {plan.label!r} starts at p = {p:.6g} {points.unit}, already at or above "
                           f"stop_at_p = {plan.stop_at_p:g} {points.unit}")
    d, tangent = plan.increment.copy(), None
    moving = np.ones(points.n, dtype=bool)
    for i in range(plan.n_increments):
        where = _Where(plan.label, i + 1)
        jump = None
        if plan.idx.size:
            target = plan.target(i)
            solved = solver.solve(solver.predict(d, plan, target, tangent), plan, target, tangent, where)
            d, tangent, calls, jump = solved.increment, solved.tangent, solved.calls, solved.jump
            fallback += solved.fallback
        else:
            update = points.trial(d)
            calls = 1
            if plan.stop_at_p is not None:
                crossing = moving & (points.mean(update.stress) >= plan.stop_at_p)
                if not crossing.any():
                    points.accept(update, None if points.n == 1 else moving)
                else:
                    points.accept(update, moving & ~crossing)
                    extra, missed = solver.land_on_p(d, crossing, update, plan.stop_at_p, where)
                    calls, fallback = calls + extra, fallback + missed
                moving &= ~crossing
            else:
                points.accept(update)
        history.record(points, calls, stage, jump)
        points.end_increment()
        if progress is not None:
            progress(plan, points)
        if plan.stop_at_p is not None and not moving.any():
            return fallback, moving
        if snapshot_interval and history.k % snapshot_interval == 0:
            history.snapshot(points, stage)
    if plan.stop_at_p is not None:
        if solver.policy.strict:
            raise ControlError(f"step {plan.label!r} ended at p = {float(points.mean(points.stress)[0]):.6g} "
                               f"{points.unit} before reaching {plan.stop_at_p:g} {points.unit}; allow more strain")
        return fallback, moving
    return fallback, np.zeros(points.n, dtype=bool)


class _Where:
    """``step 'label', increment i``, written only where an error names it."""

    def __init__(self, label: str, increment: int) -> None:
        self.label, self.increment = label, increment

    def __format__(self, spec: str) -> str:
        return f"step {self.label!r}, increment {self.increment}"


def run_stages(solver: StressControl, stages: Iterable[Step | Plan], history: History, *, snapshot_interval: int = 0,
               progress: StageProgress | None = None,
               before_stage: Mapping[int, Callable[[MaterialPoints], None]] | None = None,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``stages`` in turn on ``solver.points`` from their present state; a ``Step`` of a programme
    becomes its ``Plan`` from the stresses at its start. A snapshot closes every stage.

    Args:
        solver: the stress-control solver of the points.
        stages: programme steps (``homogenization.element_test.programme``) or plans.
        history: where the increments are recorded.
        snapshot_interval: also snapshot every this many increments (0: at stage ends only).
        progress: ``progress(plan)`` -> a context that gives the per-increment callback of that stage
            (e.g. a progress bar, closed at the stage's end).
        before_stage: stage index -> what to do to the points before that stage (e.g. erode their cells,
            ``MaterialPoints.replace_cells``); the run goes on from the changed state.

    Returns:
        The wall time of each stage [s], shape (n_stages,), and per point the fallbacks of ``run_stage`` (summed)
        and whether a stage that stops on p left it short of its stop.
    """
    points = solver.points
    stages = tuple(stages)
    seconds = np.zeros(len(stages))
    fallback = np.zeros(points.n, dtype=np.int64)
    unreached = np.zeros(points.n, dtype=bool)
    for stage, item in enumerate(stages):
        start = time.perf_counter()
        if before_stage and stage in before_stage:
            before_stage[stage](points)
        if isinstance(item, Step) and item.dim != points.dim:
            raise ValueError(f"step {item.label!r} controls {item.dim} components; the cells are {points.dim}D")
        plan = Plan.from_step(item, points.stress, points.n_voigt) if isinstance(item, Step) else item
        with nullcontext() if progress is None else progress(plan) as callback:
            missed, short = run_stage(solver, plan, history, stage, snapshot_interval=snapshot_interval,
                                      progress=callback)
        fallback += missed
        unreached |= short
        history.snapshot(points, stage)
        seconds[stage] = time.perf_counter() - start
    return seconds, fallback, unreached
