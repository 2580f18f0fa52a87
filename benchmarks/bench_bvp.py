"""python benchmarks/bench_bvp.py [--orientations 72] [--meshes 4,8 8,16] [--eps-max 0.05]

Speed of the finite-element biaxial specimen with the analytical homogenised material
(alpha0 = 40 deg, p0 = 5.85e6 N/m, 20 isotropic steps, shear at 1e-3 to --eps-max), side by
side in one run: per mesh the wall time, the material updates (Newton iterations + 1 per
step), material-point updates per second and cell-steps per second; and, on the largest
mesh's batch, the cost of one material update with and without the consistent tangent.
Prints the machine load, since timings on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from homogenization.fe import solver as fe
from homogenization.material import orientation
from homogenization.backends import make_cell_model
from homogenization.cli.bvp import element_counts
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.mesostructures.hcell import h_cell

P0 = 5.85e6
ALPHA0 = 40.0


def run_mesh(nx: int, ny: int, n_orientations: int, eps_max: float) -> tuple[float, int, int, int]:
    """Wall time [s], material updates, points and cells of one homogeneous run."""
    specimen = fe.BiaxialSpecimen(nx, ny)
    material = HomogenisedMaterial(make_cell_model("analytical"), orientation.orientations(n_orientations),
                                   h_cell(ALPHA0), specimen.n_points)
    n_shear = round(eps_max / 1e-3)
    steps = fe.isotropic_stage(P0, 20) + fe.shear_stage(P0, n_shear * 1e-3, n_shear)
    start = time.perf_counter()
    results = specimen.run(material, steps, scale=P0)
    elapsed = time.perf_counter() - start
    return elapsed, sum(r.iterations + 1 for r in results), specimen.n_points, material.n_cells


def tangent_overhead(n_points: int, n_orientations: int, repeat: int = 5) -> tuple[float, float]:
    """Seconds per material update of ``n_points`` sheared points without and with the tangent."""
    material = HomogenisedMaterial(make_cell_model("analytical"), orientation.orientations(n_orientations),
                                   h_cell(ALPHA0), n_points)
    state = material.init_state()
    for _ in range(10):
        state = material.update(state, np.tile([2e-3, 2e-3, 0.0], (n_points, 1)), with_tangent=False).state
    d_e = np.tile([1e-3, -4e-4, 0.0], (n_points, 1))
    times = []
    for with_tangent in (False, True):
        start = time.perf_counter()
        for _ in range(repeat):
            material.update(state, d_e, with_tangent=with_tangent)
        times.append((time.perf_counter() - start) / repeat)
    return times[0], times[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--orientations", type=int, default=72)
    parser.add_argument("--meshes", type=element_counts, nargs="+", default=[(4, 8), (8, 16)])
    parser.add_argument("--eps-max", type=float, default=0.05)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")
    print("mesh | wall [s] | material updates | points | material-point updates/s | cell-steps/s")
    largest = 0
    for nx, ny in args.meshes:
        elapsed, updates, points, cells = run_mesh(nx, ny, args.orientations, args.eps_max)
        largest = max(largest, points)
        print(f"{nx}x{ny} | {elapsed:.1f} | {updates} | {points} | {updates * points / elapsed:.3g} | "
              f"{updates * cells / elapsed:.3g}")
    plain, with_tangent = tangent_overhead(largest, args.orientations)
    print(f"one update of {largest} points x {args.orientations} cells: {plain * 1e3:.1f} ms without tangent, "
          f"{with_tangent * 1e3:.1f} ms with ({with_tangent / plain:.2f}x)")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
