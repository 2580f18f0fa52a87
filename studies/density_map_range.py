"""Where the void-ratio map should end: the opening angles over which the cells contract, liquefy and dilate.

For the planar H-cell (``hcell``) at several p0 and the ten-sphere ``hcell3d-sand`` cell at 2e5 Pa, closed
form, default contact law (phi_g = 30 deg): for each alpha0, undrained (2D: constant volume) compression
to eps1 = --eps-max after isotropic compression to p0, the lowest and the final p/p0; and drained
compression, eps_v at the end (> 0: contraction; "stopped" where stress control found no drained path). Then the liquefying window (lowest p/p0 < 0.3), and
the map's angles (``homogenization.material.density.OPENING_RANGE_DEG``) with the alpha0 of its loose
third. Prints and writes ``studies/results/density_map_range.txt``.

Usage: python studies/density_map_range.py [--eps-max 0.15] [--increment 1e-3]
Units: p0 in N/m (2D) and Pa (3D), strains [-], compression positive.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.calibration.forward import SHEAR_TESTS
from homogenization.element_test import driver
from homogenization.element_test.solver import ControlError
from homogenization.material.density import OPENING_RANGE_DEG
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.builders import resolve_mesostructure

ANGLES = (40.0, 44.0, 47.0, 49.0, 50.0, 51.0, 52.0, 53.0, 54.0, 55.0, 56.0, 57.0, 58.0, 59.0, 59.9)
CASES = (("hcell", 2, 5e4), ("hcell", 2, 2e5), ("hcell", 2, 5.85e6), ("hcell3d-sand", 3, 2e5))
OUT = Path(__file__).resolve().parent / "results" / "density_map_range.txt"


def run(kind: str, dim: int, p0: float, alpha0: float, drained: bool, eps_max: float, increment: float) -> driver.Record:
    """One closed-form test of cell ``kind`` at ``alpha0``; 180 planar orientations or Lebedev 11 x 1 spin."""
    programme = SHEAR_TESTS[dim](p0, eps_max, increment, iso_increment=increment / 2, drained=drained)
    return driver.run(make_cell_model("analytical", dim=dim), programme, mesostructure=resolve_mesostructure(kind, alpha0),
                      n_orientations=180, lebedev_order=11, n_spins=1, progress=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eps-max", type=float, default=0.15)
    parser.add_argument("--increment", type=float, default=1e-3)
    args = parser.parse_args()
    lines = [f"closed form, phi_g = 30 deg, to eps1 = {args.eps_max:g} in increments of {args.increment:g}",
             "liquefying: lowest p/p0 < 0.3 (undrained); eps_v > 0 is contraction (drained)"]
    for kind, dim, p0 in CASES:
        lines += ["", f"{kind} ({dim}D), p0 = {p0:g}", "alpha0  undrained min p/p0  end p/p0  drained eps_v"]
        window = []
        for alpha0 in (a for a in ANGLES if a > (dimension(dim).min_opening_deg or 0.0)):
            undrained = run(kind, dim, p0, alpha0, False, args.eps_max, args.increment)
            try:
                eps_v = f"{run(kind, dim, p0, alpha0, True, args.eps_max, args.increment).eps_v[-1]:+13.4f}"
            except ControlError as exc:  # no unique drained path past the peak (docs/triaxial.md)
                eps_v = f"  stopped ({str(exc).split(':')[0]})"
            p = undrained.p[undrained.stage == "shear"] / p0
            lines.append(f"{alpha0:6.1f}  {p.min():17.3f}  {p[-1]:8.3f}  {eps_v}")
            if p.min() < 0.3:
                window.append(alpha0)
            print(lines[-1], flush=True)
        dense, loose = OPENING_RANGE_DEG[dim]
        third = loose - (loose - dense) / 3.0
        lines.append(f"liquefying: {min(window):g}-{max(window):g} deg of the angles run" if window else "liquefying: none")
        lines.append(f"map {dense:g}-{loose:g} deg: its loose third is {third:.2f}-{loose:g} deg")
        print(*lines[-2:], sep="\n", flush=True)
    OUT.write_text("\n".join(lines) + "\n")
    print(f"-> {OUT}")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
