"""python benchmarks/bench_generate.py [--samples 300000] [--mesostructure FILE] [--out-dir DIR]

Wall time of the database generator (``warp_hcell.database.generate.generate``, the code path of
``python -m warp_hcell.generate``) on the same mesostructure, seed and settings, run side by
side in one process with several executions (``warp_hcell.core.execution``): in process with 2
Warp threads (``--workers 1``), a Dask LocalCluster of 1 and of 2 single-threaded workers
(``--workers 2`` uses the latter), and the standard-library process pool of 2 workers that
ran the chunks before Dask. Prints per execution the exploration time, the probing-and-writing
time, the total, samples/s, the speed-up over the first execution, and whether the database
files are byte-identical (they must be). The load average is printed with the numbers:
timings on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from warp_hcell.database import format as database, generate
from warp_hcell.core.execution import DaskExecution, InProcess
from warp_hcell.mesostructures.hcell import StartCells, h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.core.parameters import CellDefaults, DatabaseSettings


_SHARED: dict = {}


def _keep_shared(shared) -> None:
    _SHARED["value"] = shared


def _call_with_shared(fn, item):
    return fn(_SHARED["value"], item)


class ProcessPool:
    """The standard-library process pool that ran the chunks before Dask: ``workers`` spawned
    processes per ``map``, ``shared`` passed once per process (an execution of
    ``warp_hcell.core.execution``'s interface, kept here for the comparison)."""

    def __init__(self, workers: int = 2):
        self.n_workers = int(workers)

    def map(self, fn, shared, items):
        """Yield ``(item, fn(shared, item))`` as the tasks complete."""
        items = list(items)
        if not items:
            return
        with ProcessPoolExecutor(self.n_workers, mp_context=get_context("spawn"), initializer=_keep_shared,
                                 initargs=(shared,)) as pool:
            futures = {pool.submit(_call_with_shared, fn, item): item for item in items}
            for future in as_completed(futures):
                yield futures[future], future.result()

    def close(self) -> None:
        """Nothing to release (pools live for one ``map``)."""

    def __enter__(self) -> "ProcessPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

EXECUTIONS = (("in process", 2, lambda: InProcess()), ("dask, 1 worker", 1, lambda: DaskExecution(workers=1)),
              ("dask, 2 workers", 1, lambda: DaskExecution(workers=2)), ("process pool, 2", 1, lambda: ProcessPool(2)))
"""(label, Warp threads per process, execution factory) of each timed run."""


def timed_run(meso, starts, settings: DatabaseSettings, out: Path, make, threads: int) -> dict:
    """Generate ``out`` from scratch; returns the exploration and probing(+writing) times [s]
    (cluster start-up included in the exploration time)."""
    out.unlink(missing_ok=True)
    t0 = time.perf_counter()
    with make() as execution:
        generate.generate(meso, settings, out, seed=0, starts=starts, execution=execution, threads=threads,
                          max_chunks=0, discard_partial=True)  # exploration only (checkpointed in the sidecar)
        t1 = time.perf_counter()
        generate.generate(meso, settings, out, seed=0, starts=starts, execution=execution, threads=threads)
    t2 = time.perf_counter()
    return {"explore": t1 - t0, "probe": t2 - t1, "total": t2 - t0, "sha256": hashlib.sha256(out.read_bytes()).hexdigest()}


def differences(a: Path, b: Path) -> list[str]:
    """Names of the root attrs and datasets whose values differ between two databases."""
    data_a, attrs_a = database.read_database(a)
    data_b, attrs_b = database.read_database(b)
    names = [f"attr {k}" for k in sorted(set(attrs_a) | set(attrs_b)) if str(attrs_a.get(k)) != str(attrs_b.get(k))]
    return names + [k for k in sorted(set(data_a) | set(data_b))
                    if k not in data_a or k not in data_b or not np.array_equal(data_a[k], data_b[k], equal_nan=True)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[2],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--samples", type=int, default=300_000, help="samples per run")
    parser.add_argument("--mesostructure", type=Path, default=None, help="mesostructure file; unset: the H-cell")
    parser.add_argument("--out-dir", type=Path, default=None, help="folder for the databases; unset: a temporary one")
    args = parser.parse_args()
    settings = DatabaseSettings(samples=args.samples)
    if args.mesostructure is None:
        meso, starts = h_cell(CellDefaults.alpha0_deg, CellDefaults.radius), StartCells().build()
    else:
        meso = load_mesostructure(args.mesostructure)
        starts = [meso]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out_dir or Path(tmp)
        results = [(label, threads, timed_run(meso, starts, settings, folder / f"bench_{i}.h5", make, threads))
                   for i, (label, threads, make) in enumerate(EXECUTIONS)]
        # provenance holds the git revision: a commit during the benchmark changes the bytes (not the data)
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {meso.name}; "
              f"{args.samples} samples, {len(starts)} start cells")
        print(f"{'execution':16s} {'threads':>7s} {'explore [s]':>11s} {'probe+write [s]':>15s} {'total [s]':>10s} "
              f"{'samples/s':>10s} {'speed-up':>9s}")
        first = results[0][2]["total"]
        for label, threads, r in results:
            print(f"{label:16s} {threads:7d} {r['explore']:11.1f} {r['probe']:15.1f} {r['total']:10.1f} "
                  f"{args.samples / r['total']:10.0f} {first / r['total']:9.2f}")
        same = all(r["sha256"] == results[0][2]["sha256"] for *_, r in results)
        print(f"databases byte-identical across executions: {same}")
        if not same:
            for i in range(1, len(results)):
                print(f"{results[i][0]} vs {results[0][0]}: differs in "
                      f"{differences(folder / 'bench_0.h5', folder / f'bench_{i}.h5') or 'nothing but bytes'}")


if __name__ == "__main__":
    main()
