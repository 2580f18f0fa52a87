"""Run: python tests/yade/make_reference3d_hertz.py [--out tests/data/yade3d_hertz] [--case NAME ...]

YADE references of the ten-sphere H-cell with the Hertz-Mindlin contact law (YADE's
Ip2_FrictMat_FrictMat_MindlinPhys and Law2_ScGeom_MindlinPhys_Mindlin), written like those of the
linear law (``make_reference3d.py``: the cell, path and settings files, then
tests/yade/cell3d_paths.py under ``yade``, producing ``<case>.yade.csv`` and ``<case>.json``).
``CASES`` is the single definition of the cases, also used by tests/test_yade_reference3d_hertz.py.

Grains: r = 0.5 m, G = 29 GPa, nu = 0.2, phi_g = 30 deg (the defaults of
``warp_hcell.core.parameters.HertzMindlinLaw``). Cases (cell strain increments (d_eps_n, d_eps_t1,
d_eps_t2) [-], compression positive; 2e-5 per row: mean stresses of 0.02 to 1 MPa):
- ``hertz_axial3d_a55``: along n at constant width: load to 0.1 %, unload to 0.04 %, reload to 0.12 %;
- ``hertz_cv3d_a55``: isotropic rows of 2e-5 to 0.02 %, then isochoric rows d_eps_n = 4e-5,
  d_eps_t1 = d_eps_t2 = 1 - 1/sqrt(1 - 4e-5) to 1 % (the type-1 contacts slide).
The YADE settings are the slow, accurate ones of the linear references; the time step is
0.2 sqrt(m / k) with k the Hertz tangent stiffness at an overlap of 2e-3 (r_i + r_j), as the
package's DEM takes it.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_reference import regenerate  # noqa: E402 (tests/yade is not a package)
from make_reference3d import RADIUS, YADE_SETTINGS, Case, isochoric, run_case, write_inputs  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE.parent / "data" / "yade3d_hertz"
CONTACT_LAW = {"law": "hertz-mindlin", "shear_modulus": 29e9, "poisson": 0.2, "phi_g_deg": 30.0}
"""Contact law of the YADE runs."""
DT_OVERLAP = 2e-3
"""Overlap / (r_i + r_j) at which the time step's stiffness is taken [-]."""


def dt_stiffness(law: dict, radius: float = RADIUS) -> float:
    """Hertz tangent stiffness 1.5 (4/3) E* sqrt(R* delta) [N/m] of two spheres of ``radius`` at delta =
    DT_OVERLAP 2 r; E* = G / (1 - nu), R* = r / 2."""
    e_star = law["shear_modulus"] / (1.0 - law["poisson"])
    return 1.5 * 4.0 / 3.0 * e_star * math.sqrt(0.5 * radius * DT_OVERLAP * 2.0 * radius)


CASES: dict[str, Case] = {
    "hertz_axial3d_a55": Case(55.0, (((2e-5, 0.0, 0.0), 50), ((-2e-5, 0.0, 0.0), 30), ((2e-5, 0.0, 0.0), 40))),
    "hertz_cv3d_a55": Case(55.0, (((2e-5, 2e-5, 2e-5), 10), (isochoric(4e-5), 250))),
}
"""Reference cases by name."""


def write_case(name: str, out_dir: Path) -> Path:
    """Write the cell, path and settings files of case ``name``; return the output prefix."""
    settings = {**YADE_SETTINGS, "dt_stiffness": dt_stiffness(CONTACT_LAW)}
    return write_inputs(CASES[name], out_dir / name, CONTACT_LAW, settings)


def generate(name: str, out_dir: Path, yade: str = "yade") -> Path:
    """Write the inputs of ``name`` and run YADE on them in ``out_dir``; return the output prefix."""
    return run_case(write_case(name, out_dir), yade)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    return regenerate(argv, "Regenerate the YADE Hertz-Mindlin reference cases of the ten-sphere H-cell.", DATA_DIR,
                      CASES, generate)


if __name__ == "__main__":
    sys.exit(main())
