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
from dataclasses import dataclass
from typing import Any, Callable, ContextManager, Iterable, Mapping

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


@dataclass
class StageState:
    """Where a stage's increments are (what a checkpoint keeps of a stage under way).

    Attributes:
        done: increments of the stage recorded.
        d: the next increment's first guess of every point, shape (n, n_voigt) [-].
        tangent: the last tangent of every point (``solver.Solved.tangent``), None before one.
        moving: per point, not yet landed on the stage's stop on p, shape (n,).
        fallback: per point, the stage's increments that took an unconverged iterate, shape (n,).
    """

    done: int
    d: np.ndarray
    tangent: np.ndarray | None
    moving: np.ndarray
    fallback: np.ndarray


def run_stage(solver: StressControl, plan: Plan, history: History, stage: int, *, snapshot_interval: int = 0,
              progress: Progress | None = None, at: StageState | None = None,
              after: Callable[[StageState], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run the increments of ``plan`` on ``solver.points`` from its start (``at`` None) or from ``at``;
    ``after(state)`` is called after every recorded increment. Returns per point the increments where an
    unconverged iterate was taken, and whether a stage that stops on p ended before reaching it (both under
    a non-strict policy only; a strict one raises).

    Raises:
        homogenization.element_test.solver.ControlError: (strict policy) a stress-controlled increment
            or landing did not converge, or a stage that stops on p starts at or above it or ends before
            reaching it.
    """
    points = solver.points
    if at is None:
        if plan.stop_at_p is not None and np.any(points.mean(points.stress) >= plan.stop_at_p):
            p = float(points.mean(points.stress).max())
            raise ControlError(f"step {plan.label!r} starts at p = {p:.6g} {points.unit}, already at or above "
                               f"stop_at_p = {plan.stop_at_p:g} {points.unit}")
        at = StageState(0, plan.increment.copy(), None, np.ones(points.n, dtype=bool),
                        np.zeros(points.n, dtype=np.int64))
    elif plan.stop_at_p is not None and not at.moving.any():
        return at.fallback, at.moving
    for i in range(at.done, plan.n_increments):
        where = _Where(plan.label, i + 1)
        jump = None
        if plan.idx.size:
            target = plan.target(i)
            solved = solver.solve(solver.predict(at.d, plan, target, at.tangent), plan, target, at.tangent, where)
            at.d, at.tangent, calls, jump = solved.increment, solved.tangent, solved.calls, solved.jump
            at.fallback = at.fallback + solved.fallback
        else:
            update = points.trial(at.d)
            calls = 1
            if plan.stop_at_p is not None:
                crossing = at.moving & (points.mean(update.stress) >= plan.stop_at_p)
                if not crossing.any():
                    points.accept(update, None if points.n == 1 else at.moving)
                else:
                    points.accept(update, at.moving & ~crossing)
                    extra, missed = solver.land_on_p(at.d, crossing, update, plan.stop_at_p, where)
                    calls, at.fallback = calls + extra, at.fallback + missed
                at.moving = at.moving & ~crossing
            else:
                points.accept(update)
        history.record(points, calls, stage, jump)
        points.end_increment()
        at.done = i + 1
        if progress is not None:
            progress(plan, points)
        if plan.stop_at_p is not None and not at.moving.any():
            if after is not None:
                after(at)
            return at.fallback, at.moving
        if snapshot_interval and history.k % snapshot_interval == 0:
            history.snapshot(points, stage)
        if after is not None:
            after(at)
    if plan.stop_at_p is not None:
        if solver.policy.strict:
            raise ControlError(f"step {plan.label!r} ended at p = {float(points.mean(points.stress)[0]):.6g} "
                               f"{points.unit} before reaching {plan.stop_at_p:g} {points.unit}; allow more strain")
        return at.fallback, at.moving
    return at.fallback, np.zeros(points.n, dtype=bool)


class _Where:
    """``step 'label', increment i``, written only where an error names it."""

    def __init__(self, label: str, increment: int) -> None:
        self.label, self.increment = label, increment

    def __format__(self, spec: str) -> str:
        return f"step {self.label!r}, increment {self.increment}"


def run_stages(solver: StressControl, stages: Iterable[Step | Plan], history: History, *, snapshot_interval: int = 0,
               progress: StageProgress | None = None,
               before_stage: Mapping[int, Callable[[MaterialPoints], None]] | None = None,
               checkpoint: Any = None, resume: tuple[int, np.ndarray, StageState | None, np.ndarray] | None = None,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``stages`` in turn on ``solver.points`` from their present state; a ``Step`` becomes its ``Plan``
    from the stresses at its start. A snapshot closes every stage.

    Args:
        solver: the stress-control solver of the points.
        stages: programme steps (``homogenization.element_test.programme``) or plans.
        history: where the increments are recorded.
        snapshot_interval: also snapshot every this many increments (0: at stage ends only).
        progress: ``progress(plan)`` (a resumed stage: ``progress(plan, done=k)``) -> a context giving the
            stage's per-increment callback.
        before_stage: stage index -> what to do to the points before it (e.g. an erosion).
        checkpoint: saves the run after an increment where due (``checkpoint.RunCheckpoint``); None: none.
        resume: where a checkpoint left the run (``RunCheckpoint.load``); None: from the first stage.

    Returns:
        The wall time of each stage [s], shape (n_stages,), and per point the fallbacks of ``run_stage`` (summed)
        and whether a stage that stops on p left it short of its stop.
    """
    points = solver.points
    stages = tuple(stages)
    first, resume_stress, at, seconds = (0, None, None, np.zeros(len(stages))) if resume is None else resume
    seconds = np.array(seconds, dtype=np.float64)
    fallback = np.zeros(points.n, dtype=np.int64)
    unreached = np.zeros(points.n, dtype=bool)
    for stage in range(first, len(stages)):
        item, resumed = stages[stage], resume_stress is not None and stage == first and at is not None
        start = time.perf_counter() - seconds[stage]
        if before_stage and stage in before_stage and not resumed:
            before_stage[stage](points)
        if isinstance(item, Step) and item.dim != points.dim:
            raise ValueError(f"step {item.label!r} controls {item.dim} components; the cells are {points.dim}D")
        stress = resume_stress if resumed else points.stress
        plan = Plan.from_step(item, stress, points.n_voigt) if isinstance(item, Step) else item

        def after(state: StageState, stage: int = stage, stress: np.ndarray = stress, start: float = start) -> None:
            if checkpoint is not None and checkpoint.due():
                seconds[stage] = time.perf_counter() - start
                checkpoint.save(solver, history, stage, stress, state, seconds)

        done = at.done if resumed else 0
        context = nullcontext() if progress is None else progress(plan, done=done) if done else progress(plan)
        with context as callback:
            missed, short = run_stage(solver, plan, history, stage, snapshot_interval=snapshot_interval,
                                      progress=callback, at=at if resumed else None, after=after)
        fallback += missed
        unreached |= short
        history.snapshot(points, stage)
        seconds[stage] = time.perf_counter() - start
    if checkpoint is not None and (checkpoint.due() or checkpoint.keep_last):
        checkpoint.save(solver, history, len(stages), points.stress, None, seconds)
    return seconds, fallback, unreached
