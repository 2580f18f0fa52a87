"""Execution of independent tasks for the database generator: in process, or on Dask.

An execution runs ``fn(shared, item)`` for every item and yields ``(item, result)`` as the
tasks complete; the caller (the client) stores the results, so what is written does not
depend on where, in which order or how often (lost workers: Dask reruns their tasks) a
task ran. ``shared`` is sent once per worker (Dask: scattered with broadcast).

- ``InProcess``: the calling process, one task after the other.
- ``DaskExecution``: a ``distributed`` cluster: an existing scheduler (``address``, e.g.
  ``tcp://host:8786``; dask-jobqueue clusters on SLURM give one), or a ``LocalCluster`` of
  ``workers`` single-threaded worker processes.

``make_execution(workers, scheduler, setup)`` picks one: a scheduler address -> Dask on it;
more than one worker -> a Dask LocalCluster; else in process. ``setup()`` (optional, e.g.
silencing Warp's start-up messages) runs in the process of every task, before the task; it
must be picklable and cheap after its first call in a process.

``task_warnings()`` collects the warnings a task raises in its own thread (a worker of a remote scheduler may run
several tasks at once in threads, where ``warnings.catch_warnings`` would mix and lose them).

A LocalCluster keeps its scratch files (worker folders, locks, spilled data) in a temporary
folder of its own (under ``TMPDIR``), removed when the execution closes: a run leaves no
``dask-scratch-space`` behind.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import shutil
import tempfile
import threading
import warnings
from typing import Any, Callable, Iterable, Iterator

CONNECT_TIMEOUT_S = 10.0
"""Seconds to wait for a Dask scheduler before giving up [s]."""


_SINK = threading.local()
_SHOW_AT_IMPORT = warnings.showwarning
_CAPTURE_LOCK = threading.Lock()
_capturing = {"threads": 0, "saved": None}


def _show(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` while tasks collect: into the calling thread's list, or as before elsewhere."""
    lines = getattr(_SINK, "lines", None)
    if lines is None:  # (no saved one: a catch_warnings block of a thread put this back after the last block ended)
        show = _capturing["saved"][0] if _capturing["saved"] else _SHOW_AT_IMPORT
        show(message, category, filename, lineno, file, line)
    else:
        lines.append(" ".join(str(message).split()))


@contextlib.contextmanager
def task_warnings() -> Iterator[list[str]]:
    """A list that receives, as one line each, every warning raised in this thread inside the block (each time it is
    raised; a thread's own warnings only, whatever other threads do meanwhile). Warnings of threads not inside such a
    block are shown as before. Python's warning filters stay process-wide: a thread that silences warnings in a
    ``warnings.catch_warnings`` block silences every thread's meanwhile."""
    with _CAPTURE_LOCK:
        if _capturing["threads"] == 0:
            _capturing["saved"] = (warnings.showwarning, warnings.filters[:])
            warnings.showwarning = _show
            warnings.simplefilter("always")
        _capturing["threads"] += 1
    _SINK.lines = lines = []
    try:
        yield lines
    finally:
        _SINK.lines = None
        with _CAPTURE_LOCK:
            _capturing["threads"] -= 1
            if _capturing["threads"] == 0:
                warnings.showwarning, warnings.filters[:] = _capturing["saved"]
                _capturing["saved"] = None


class SchedulerUnreachable(ConnectionError):
    """The Dask scheduler at the given address did not answer."""


def _after_setup(setup: Callable[[], None], fn: Callable[[Any, Any], Any], shared: Any, item: Any) -> Any:
    """``fn(shared, item)`` after ``setup()`` (in the process that runs the task)."""
    setup()
    return fn(shared, item)


def _with_setup(fn: Callable[[Any, Any], Any], setup: Callable[[], None] | None) -> Callable[[Any, Any], Any]:
    """``fn``, or ``fn`` preceded by ``setup()`` in every task (picklable: a partial of module functions)."""
    return fn if setup is None else functools.partial(_after_setup, setup, fn)


class InProcess:
    """Run the tasks in the calling process, in order (``setup`` before each)."""

    n_workers = 1

    def __init__(self, setup: Callable[[], None] | None = None):
        self.setup = setup

    def map(self, fn: Callable[[Any, Any], Any], shared: Any, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Yield ``(item, fn(shared, item))`` for every item, in order."""
        task = _with_setup(fn, self.setup)
        for item in items:
            yield item, task(shared, item)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> "InProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaskExecution:
    """Run the tasks on a Dask cluster (module docstring).

    Args:
        address: scheduler address; None = start a LocalCluster.
        workers: worker processes of the LocalCluster (one thread each).
        connect_timeout: seconds to wait for the scheduler [s]; None = ``CONNECT_TIMEOUT_S``.
        setup: run before every task, in the worker (module docstring).

    Raises:
        SchedulerUnreachable: (one line) no scheduler answers at ``address``.
    """

    def __init__(self, address: str | None = None, workers: int = 2, connect_timeout: float | None = None,
                 setup: Callable[[], None] | None = None):
        import dask  # noqa: PLC0415 (optional at import time)
        from distributed import Client, LocalCluster  # noqa: PLC0415

        for name in ("distributed", "tornado"):
            logging.getLogger(name).setLevel(logging.ERROR)
        self.setup = setup
        self._cluster = None
        self._scratch = None
        if address is None:
            self._scratch = tempfile.mkdtemp(prefix="hmodel-dask-")
            try:
                # the scheduler's and the workers' scratch folders (dask's temporary-directory)
                with dask.config.set({"temporary-directory": self._scratch}):
                    self._cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                                 dashboard_address=None, silence_logs=logging.CRITICAL)
                # task errors still reach the client; workers' shutdown-race tracebacks do not
                self.client = Client(self._cluster)
            except BaseException:
                self._close_cluster()
                raise
        else:
            try:
                timeout = CONNECT_TIMEOUT_S if connect_timeout is None else connect_timeout
                self.client = Client(address, timeout=f"{timeout}s")
            except (OSError, TimeoutError, ValueError, TypeError) as exc:
                message = " ".join(str(exc).split()) or type(exc).__name__
                raise SchedulerUnreachable(f"cannot reach the Dask scheduler at {address}: {message}") from None

    @property
    def n_workers(self) -> int:
        """Workers connected now."""
        return len(self.client.scheduler_info().get("workers", {}))

    def map(self, fn: Callable[[Any, Any], Any], shared: Any, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Submit ``fn(shared, item)`` for every item; yield ``(item, result)`` as they complete."""
        from distributed import as_completed  # noqa: PLC0415

        items = list(items)
        if not items:
            return
        shared_future = self.client.scatter(shared, broadcast=True, hash=False)
        task = _with_setup(fn, self.setup)
        futures = {self.client.submit(task, shared_future, item, pure=False): item for item in items}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        finally:
            for future in futures:
                future.cancel()
            shared_future.cancel()

    def close(self) -> None:
        """Disconnect; stop the LocalCluster if this execution started it and remove its scratch folder."""
        self.client.close()
        self._close_cluster()

    def _close_cluster(self) -> None:
        if self._cluster is not None:
            self._cluster.close()
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)

    def __enter__(self) -> "DaskExecution":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_execution(workers: int = 1, scheduler: str | None = None,
                   setup: Callable[[], None] | None = None) -> InProcess | DaskExecution:
    """Dask on ``scheduler``; else a Dask LocalCluster of ``workers`` processes; one worker: in
    process. ``setup`` runs before every task, where the task runs (module docstring)."""
    if scheduler is not None:
        return DaskExecution(address=scheduler, setup=setup)
    if int(workers) > 1:
        return DaskExecution(workers=int(workers), setup=setup)
    return InProcess(setup)
