"""Progress bars of the element test's stages, as the run commands draw them: ``driver.run(...,
progress=stage_bars)`` draws one bar per stage that counts its increments (``progress_bar``: plain
lines where stderr is no terminal, nothing under -q).
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from homogenization.element_test.plan import Plan
from homogenization.element_test.points import MaterialPoints
from homogenization.element_test.stages import Progress
from warp_hcell.core.cli import progress_bar


@contextlib.contextmanager
def stage_bars(plan: Plan, done: int = 0) -> Iterator[Progress]:
    """A progress bar of the stage ``plan`` while the body runs, starting at ``done`` increments (a resumed
    stage); gives the per-increment callback that advances it. A stage that stops on p has no known length:
    its bar has no total and shows p as a percentage of stop_at_p."""
    total = None if plan.stop_at_p is not None else plan.n_increments
    with progress_bar(total=total, initial=done, desc=plan.label, unit="incr", leave=False) as shown:
        def advance(_plan: Plan, points: MaterialPoints) -> None:
            if plan.stop_at_p is not None and not shown.disable:
                p = float(points.mean(points.stress)[0])
                shown.set_postfix_str(f"p = {p / plan.stop_at_p:.1%} of {plan.stop_at_p:g} {points.unit}",
                                      refresh=False)
            shown.update(1)
        yield advance
