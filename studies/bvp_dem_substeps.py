"""python studies/bvp_dem_substeps.py [--elements 1,2] [--orientations 72] [--shear-steps 60]

What sets the DEM's substeps per cell and material update in the FE biaxial specimen
(``homogenization.fe.solver``, alpha0 = 40 deg, p0 = 2e5 N/m, 20 isotropic steps, then shear
steps of 1e-3): every update of the run is stepped a second time from the same state with the
same increment and the force tolerance set to 1e30, so that the cells stop as soon as the
driving ends; that run's substeps are the driving substeps, the difference to the real run's the
relaxation (the early stop once balanced). Prints, per stage, the mean substeps per cell and
update, split into driving and relaxation, their medians and the 90th percentile of the driving
substeps, and every sixth shear update with its largest cell strain increment.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.cli.bvp import element_counts
from homogenization.fe import solver as fe
from homogenization.material import orientation
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.dem.cell import DemCell, DemCellState
from warp_hcell.mesostructures.hcell import h_cell

P0 = 2e5


class SplitSubsteps(DemCell):
    """The DEM backend recording, per step, its substeps and those of the driving alone."""

    def __init__(self) -> None:
        base = make_cell_model("dem")
        super().__init__(base.contact_law, base.radius)
        self.drive_only = make_cell_model("dem")
        self.log: list[tuple[float, float, float, float, float, float]] = []

    def step(self, state, d_eps_local, *, with_tangent=False):
        new, response = super().step(state, d_eps_local, with_tangent=with_tangent)
        model = replace(state.model, settings=replace(state.model.settings, force_tolerance=1e30))
        driven, _ = self.drive_only.step(DemCellState(model, state.dem), d_eps_local)
        total, drive = new.dem.substeps.numpy(), driven.dem.substeps.numpy()
        self.log.append((float(np.abs(d_eps_local).max()), total.mean(), drive.mean(), float(np.median(total)),
                         float(np.median(drive)), float(np.percentile(drive, 90))))
        return new, response


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=element_counts, default=(1, 2))
    parser.add_argument("--orientations", type=int, default=72)
    parser.add_argument("--shear-steps", type=int, default=60)
    args = parser.parse_args()
    model = SplitSubsteps()
    specimen = fe.BiaxialSpecimen(*args.elements, newton_rtol=1e-5)
    material = HomogenisedMaterial(model, orientation.orientations(args.orientations), h_cell(40.0),
                                   specimen.n_points)
    steps = fe.isotropic_stage(P0, 20) + fe.shear_stage(P0, args.shear_steps * 1e-3, args.shear_steps)
    results = specimen.run(material, steps, scale=P0)
    log = np.array(model.log)
    shear_updates = sum(r.iterations + 1 for r in results if r.stage == "shear")
    iso = np.arange(len(log)) < len(log) - shear_updates
    peak = max((r.sigma11 - r.sigma22) / P0 for r in results)
    print(f"{args.elements[0]} x {args.elements[1]} elements, {material.n_cells} cells, 20 + {args.shear_steps} "
          f"steps, {len(log)} updates; peak q/p0 {peak:.4f}")
    for name, mask in (("iso", iso), ("shear", ~iso)):
        total, drive = log[mask, 1].mean(), log[mask, 2].mean()
        print(f"{name}: {mask.sum()} updates, mean substeps per cell {total:.1f}: driving {drive:.1f}, relaxation "
              f"{total - drive:.1f}; median total {np.median(log[mask, 3]):.0f}, "
              f"driving {np.median(log[mask, 4]):.0f}; "
              f"90th percentile of driving (median over updates) {np.median(log[mask, 5]):.0f}")
    for k in np.flatnonzero(~iso)[::6]:
        print(f"  shear update {k}: largest cell strain increment {log[k, 0]:.2e}, mean substeps {log[k, 1]:.1f}, "
              f"driving {log[k, 2]:.1f}")


if __name__ == "__main__":
    main()
