"""A real Dask scheduler and workers on 127.0.0.1 for tests of the distributed execution.

``local_cluster(n_workers, env, cwd)`` starts ``dask scheduler`` and ``n_workers`` single-thread
``dask worker`` processes (their output discarded), waits until every worker has joined, and
yields ``(address, processes)``; ``processes[1 + i]`` is worker i, so a test can kill one. Every
process is killed on exit. ``free_port()`` is a TCP port nothing listens on.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Mapping

from warp_hcell.core import execution


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (just released by the OS)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def local_cluster(n_workers: int, env: Mapping[str, str], cwd: Path | None = None
                  ) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """Scheduler plus ``n_workers`` workers; yields (address, [scheduler, worker 0, ...])."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"env": dict(env), "cwd": cwd, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], **quiet)]
    try:
        procs += [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                    "--no-nanny", "--no-dashboard", "--name", f"w{i}"], **quiet)
                  for i in range(n_workers)]
        with execution.DaskExecution(address=address, connect_timeout=30.0) as dask:
            dask.client.wait_for_workers(n_workers, timeout=60)
        yield address, procs
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
