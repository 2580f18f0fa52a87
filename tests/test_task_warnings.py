"""``warp_hcell.core.execution.task_warnings``: each thread collects its own warnings, as tasks of a Dask worker that
runs several threads do (``warnings.catch_warnings`` mixed them: a task's warning went to another task's list, or to
the terminal once the other's block had ended)."""

from __future__ import annotations

import threading
import warnings

from warp_hcell.core.execution import task_warnings


def test_threads_collect_their_own_warnings_each_time_they_are_raised():
    names, results, barrier = ("a", "b", "c"), {}, threading.Barrier(3)

    def task(name: str) -> None:
        with task_warnings() as caught:
            for k in range(4):
                barrier.wait()  # every thread inside its block, raising in turn
                warnings.warn(f"task {name}\n  warns", RuntimeWarning)
            barrier.wait()  # none leaves its block before the others have raised
        results[name] = caught

    threads = [threading.Thread(target=task, args=(name,)) for name in names]
    with warnings.catch_warnings(record=True) as outside:
        warnings.simplefilter("always")
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        warnings.warn("after the tasks", UserWarning)  # shown as before the blocks
    assert results == {name: [f"task {name} warns"] * 4 for name in names}
    assert [str(w.message) for w in outside] == ["after the tasks"]
