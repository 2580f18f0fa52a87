"""python studies/bench_dem_tangent.py [--rate 1e-8] [--orientations 36]

How the DEM step's own derivative relates to the condensed tangent (docs/bvp.md, section 1).

1. H-cells alpha0 = 35-70 deg, sheared at constant volume (the fixture of
   tests/test_warp_hcell_tangent.py), probed by the next increment with its t component
   1.1 times larger, force tolerance 1e-13, --rate strain per substep: per cell the relative
   error of the condensed tangent against central differences of the step, column by column
   (the largest strain component, which sets the driving substeps, and the other one), plain
   and at a held driving schedule (tests/tangent_fd.py).
2. Drained biaxial (alpha0 = 40 deg, p0 = 2e5, increment 1e-3, default DEM settings and
   force tolerance 1e-10): step calls per shear increment and the residual ratio of
   successive Newton iterations of the driver's stress control, analytical and DEM.

Compression positive; errors relative to max |C_fd| per cell.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from tangent_fd import fd_tangent_fixed_schedule  # noqa: E402
from warp_hcell.core.checks import central_difference_tangent  # noqa: E402

from homogenization.element_test import driver, programme as programmes  # noqa: E402
from homogenization.element_test.solver import StressControl  # noqa: E402
from homogenization.backends import make_cell_model  # noqa: E402
from warp_hcell.dem.cell import DemCell  # noqa: E402
from warp_hcell.mesostructures.hcell import h_cell  # noqa: E402
from warp_hcell.core.parameters import ContactLaw, DemSettings  # noqa: E402
from warp_hcell.dem.tangent import sliding_contacts  # noqa: E402

LAW = ContactLaw()
RADIUS = 0.5


def column_errors(tangent: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per cell and strain column: max_a |C - C_fd|[a, b] / max |C_fd|, shape (n_cells, 2)."""
    return np.abs(tangent - reference).max(axis=1) / np.abs(reference).max(axis=(1, 2))[:, None]


def tangent_probe(rate: float) -> None:
    settings = DemSettings(force_tolerance=1e-13, strain_per_substep=rate, refined_strain_per_substep=rate,
                           max_substeps=10**8)
    dem = DemCell(LAW, RADIUS, settings=settings, threads=1)
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 3)
    n = alpha0.size
    c2 = np.cos(2 * np.linspace(0, np.pi / 2, n))
    state = dem.init_state([h_cell(a, RADIUS) for a in alpha0], n)
    state, _ = dem.step(state, np.full((n, 2), 1e-3))
    shear = np.stack([1e-3 * c2, -1e-3 * c2], axis=1)
    for _ in range(3):
        state, _ = dem.step(state, shear)
    d_eps = 1e-2 * shear * np.array([1.0, 1.1])
    largest = np.abs(d_eps).max(axis=1)
    d_eps *= ((np.floor(largest / rate) + 0.5) * rate / largest)[:, None]
    new, response = dem.step(state, d_eps, with_tangent=True)
    before, after = state.dem.to_numpy(), new.dem.to_numpy()
    sliding = sliding_contacts(before["position"], after["position"], state.model.radius.numpy(),
                               state.model.meso.pairs, before["shear_force"], kn=LAW.kn, kt=LAW.kt,
                               mu=LAW.mu).any(axis=1)
    h = 0.1 * rate
    plain = column_errors(response.tangent, central_difference_tangent(dem, state, d_eps, h))
    held = column_errors(response.tangent, fd_tangent_fixed_schedule(dem, state, d_eps, h))
    lead = np.abs(d_eps).argmax(axis=1)
    print(f"condensed tangent vs central differences, {rate:g} strain per substep, h = {h:g}")
    print("cell alpha0 regime | plain: largest col, other col | held schedule: largest col, other col")
    for c in range(n):
        print(f"{c:4d} {alpha0[c]:6.0f} {'slide' if sliding[c] else 'stick':6s} | {plain[c, lead[c]]:.2e} "
              f"{plain[c, 1 - lead[c]]:.2e} | {held[c, lead[c]]:.2e} {held[c, 1 - lead[c]]:.2e}")


def newton_contraction(orientations: int) -> None:
    """Residual ratios of the driver's stress-control iterations (drained shear)."""
    p0 = 2e5
    programme = programmes.biaxial(p0, 0.05, 1e-3, iso_increment=1e-4, drained=True)
    solve = StressControl.solve
    print(f"drained biaxial, alpha0 = 40 deg, p0 = {p0:g}, {orientations} orientations, increment 1e-3")
    for name, options in (("analytical", {}), ("dem", {}), ("dem, force tolerance 1e-10",
                                                         {"settings": DemSettings(force_tolerance=1e-10)})):
        histories: list[list[float]] = []

        def recording(solver, d, plan, target, tangent, where):
            residuals: list[float] = []
            points = solver.points
            trial = points.trial

            def tracked(d_e, with_tangent=False):
                update = trial(d_e, with_tangent=with_tangent)
                residuals.append(float(np.abs(plan.controlled(update.stress) - target).max()) / p0)
                return update

            points.trial = tracked
            try:
                return solve(solver, d, plan, target, tangent, where)
            finally:
                del points.trial
                histories.append(residuals)

        StressControl.solve = recording
        try:
            record = driver.run(make_cell_model(name.split(",")[0], **options), programme, mesostructure=h_cell(40.0),
                                n_orientations=orientations, progress=False)
        finally:
            StressControl.solve = solve
        shear = histories[-int((record.stage == "shear").sum()):]
        calls = np.array([len(h) for h in shear])
        ratios = np.array([h[k + 1] / h[k] for h in shear for k in range(len(h) - 1) if h[k] > 0])
        print(f"  {name}: step calls per shear increment mean {calls.mean():.2f}, max {calls.max()}; residual "
              f"ratio per iteration median {np.median(ratios):.1e}, max {ratios.max():.1e}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[2])
    parser.add_argument("--rate", type=float, default=1e-8, help="strain per substep of the tangent probe")
    parser.add_argument("--orientations", type=int, default=36, help="orientations of the drained run")
    args = parser.parse_args()
    tangent_probe(args.rate)
    newton_contraction(args.orientations)


if __name__ == "__main__":
    main()
