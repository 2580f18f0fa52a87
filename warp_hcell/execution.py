"""Execution of independent tasks for the database generator: in process, or on Dask.

An execution runs ``fn(shared, item)`` for every item and yields ``(item, result)`` as the
tasks complete; the caller (the client) stores the results, so what is written does not
depend on where, in which order or how often (lost workers: Dask reruns their tasks) a
task ran. ``shared`` is sent once per worker (Dask: scattered with broadcast).

- ``InProcess``: the calling process, one task after the other.
- ``ProcessPool``: ``workers`` local processes of the standard library (spawned per ``map``;
  ``shared`` passed once per process): the pre-Dask execution, kept for the benchmark.
- ``DaskExecution``: a ``distributed`` cluster: an existing scheduler (``address``, e.g.
  ``tcp://host:8786``; dask-jobqueue clusters on SLURM give one), or a ``LocalCluster`` of
  ``workers`` single-threaded worker processes.

``make_execution(workers, scheduler)`` picks one: a scheduler address -> Dask on it; more
than one worker -> a Dask LocalCluster; else in process.
"""

from __future__ import annotations

import logging
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, Callable, Iterable, Iterator

CONNECT_TIMEOUT_S = 10.0
"""Seconds to wait for a Dask scheduler before giving up [s]."""


class SchedulerUnreachable(ConnectionError):
    """The Dask scheduler at the given address did not answer."""


class InProcess:
    """Run the tasks in the calling process, in order."""

    n_workers = 1

    def map(self, fn: Callable[[Any, Any], Any], shared: Any, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Yield ``(item, fn(shared, item))`` for every item, in order."""
        for item in items:
            yield item, fn(shared, item)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> "InProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_SHARED: dict[str, Any] = {}


def _keep_shared(shared: Any) -> None:
    _SHARED["value"] = shared


def _call_with_shared(fn: Callable[[Any, Any], Any], item: Any) -> Any:
    return fn(_SHARED["value"], item)


class ProcessPool:
    """Run the tasks in ``workers`` spawned local processes (module docstring)."""

    def __init__(self, workers: int = 2):
        self.n_workers = int(workers)

    def map(self, fn: Callable[[Any, Any], Any], shared: Any, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Yield ``(item, fn(shared, item))`` as the tasks complete."""
        items = list(items)
        if not items:
            return
        with ProcessPoolExecutor(self.n_workers, mp_context=get_context("spawn"), initializer=_keep_shared,
                                 initargs=(shared,)) as pool:
            futures = {pool.submit(_call_with_shared, fn, item): item for item in items}
            try:
                for future in as_completed(futures):
                    yield futures[future], future.result()
            finally:
                for future in futures:
                    future.cancel()

    def close(self) -> None:
        """Nothing to release (pools live for one ``map``)."""

    def __enter__(self) -> "ProcessPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaskExecution:
    """Run the tasks on a Dask cluster (module docstring).

    Args:
        address: scheduler address; None = start a LocalCluster.
        workers: worker processes of the LocalCluster (one thread each).
        connect_timeout: seconds to wait for the scheduler [s]; None = ``CONNECT_TIMEOUT_S``.

    Raises:
        SchedulerUnreachable: (one line) no scheduler answers at ``address``.
    """

    def __init__(self, address: str | None = None, workers: int = 2, connect_timeout: float | None = None):
        from distributed import Client, LocalCluster  # noqa: PLC0415 (optional at import time)

        for name in ("distributed", "tornado"):
            logging.getLogger(name).setLevel(logging.ERROR)
        self._cluster = None
        if address is None:
            self._cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                         dashboard_address=None, silence_logs=logging.CRITICAL)
            # task errors still reach the client; workers' shutdown-race tracebacks do not
            self.client = Client(self._cluster)
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
        futures = {self.client.submit(fn, shared_future, item, pure=False): item for item in items}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        finally:
            for future in futures:
                future.cancel()
            shared_future.cancel()

    def close(self) -> None:
        """Disconnect; stop the LocalCluster if this execution started it."""
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self) -> "DaskExecution":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_execution(workers: int = 1, scheduler: str | None = None) -> InProcess | DaskExecution:
    """Dask on ``scheduler``; else a Dask LocalCluster of ``workers`` processes; one worker: in process."""
    if scheduler is not None:
        return DaskExecution(address=scheduler)
    if int(workers) > 1:
        return DaskExecution(workers=int(workers))
    return InProcess()
