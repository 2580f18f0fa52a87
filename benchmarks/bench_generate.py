"""python benchmarks/bench_generate.py [--samples 4000] [--threads 2]

Samples per second of the database generator (``warp_hcell.generate``) with the DEM backend
stepped by the Warp kernels and by the numpy engine of the same step: the same generator
code, the same small exploration tree (3 alpha0 x 3 precompressions x 8 directions, legs
of path length 0.05), the same seed and probes. Prints, per engine, the exploration time,
the probing time (all probes of a chunk in one batch), samples/s of the probing and of the
whole run, the ratios, and the largest difference between the two engines' outputs
(they run the same algorithm; the numpy engine is the reference). The load average is
printed with the numbers: timings on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import functools
import os
import time

import numpy as np

from warp_hcell import generate
from warp_hcell.parameters import CellDefaults, ContactLaw, DatabaseSettings


def run(engine: str, settings: DatabaseSettings, threads: int) -> dict:
    """Explore and probe with one DEM engine; returns timings [s] and the samples."""
    from warp_hcell.dem_cell import DemCell

    cell = functools.partial(DemCell, ContactLaw(), CellDefaults.radius, engine=engine, threads=threads)()
    start = time.perf_counter()
    states = generate.explore(cell, settings)
    explored = time.perf_counter()
    pool = cell.state_from_arrays(generate.backend_arrays(states))
    chunks = [generate.compute_chunk(cell, pool, states, settings, 0, c) for c in range(generate.n_chunks(settings))]
    probed = time.perf_counter()
    outputs = np.concatenate([chunk["outputs"] for chunk in chunks])
    return {"explore": explored - start, "probe": probed - explored, "outputs": outputs,
            "n_states": states["path_id"].size}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[2],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--samples", type=int, default=4000, help="probes per engine")
    parser.add_argument("--chunk-size", type=int, default=2000, help="probes per batch")
    parser.add_argument("--threads", type=int, default=2, help="Warp CPU threads")
    args = parser.parse_args()
    settings = DatabaseSettings(samples=args.samples, chunk_size=args.chunk_size, n_alpha0=2,
                                alpha0_focus_deg=(55.0,), precompression=(0.0, 1e-3, 1e-2), n_directions=8,
                                sample_spacing=1e-2, leg_length=0.05, leg_refinement=1)
    results = {engine: run(engine, settings, args.threads) for engine in ("warp", "numpy")}
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {args.samples} samples, "
          f"{results['warp']['n_states']} explored states, Warp threads = {args.threads}")
    print(f"{'engine':8s} {'explore [s]':>12s} {'probe [s]':>10s} {'probe samples/s':>16s} {'total samples/s':>16s}")
    for engine, r in results.items():
        total = r["explore"] + r["probe"]
        print(f"{engine:8s} {r['explore']:12.2f} {r['probe']:10.2f} {args.samples / r['probe']:16.0f} "
              f"{args.samples / total:16.0f}")
    warp, ref = results["warp"], results["numpy"]
    print(f"speed-up warp / numpy: exploration {ref['explore'] / warp['explore']:.1f}x, "
          f"probing {ref['probe'] / warp['probe']:.1f}x, "
          f"total {(ref['explore'] + ref['probe']) / (warp['explore'] + warp['probe']):.1f}x")
    scale = np.abs(ref["outputs"]).max(axis=0)
    print(f"largest |warp - numpy| / max|numpy| over outputs (alpha, N1, N2, T1): "
          f"{np.max(np.abs(warp['outputs'] - ref['outputs']) / scale):.2e}")


if __name__ == "__main__":
    main()
