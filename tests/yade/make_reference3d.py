"""Run: python tests/yade/make_reference3d.py [--out tests/data/yade3d] [--case NAME ...]

Writes, per YADE reference case of the ten-sphere H-cell, the cell (``<case>.cell.json``: radii,
centres, driven DOF mask, cell size), the strain path (``<case>.path.csv``) and the settings
(``<case>.settings.json``), and runs tests/yade/cell3d_paths.py on them with ``yade`` (must be on
PATH), producing ``<case>.yade.csv`` and ``<case>.json``. ``CASES`` is the single definition of the
cases, also used by tests/test_yade_reference3d.py.

Cases (cell strain increments (d_eps_n, d_eps_t1, d_eps_t2) [-], compression positive, rows of 1e-4
unless said):
- ``axial3d_a55``, ``axial3d_a50``: along n at constant width: load to 1 %, unload to 0.4 %, reload to
  1.2 %;
- ``lateral3d_a55``, ``lateral3d_a50``: the same along t1 only (plane A deforms, plane B keeps l3):
  the two planes take different y2;
- ``cv3d_a55``: isotropic rows of 1e-4 to 0.1 %, then isochoric rows d_eps_n = 2e-4,
  d_eps_t1 = d_eps_t2 = 1 - 1/sqrt(1 - 2e-4) to 10 %.
- ``axisym3d_a54_axial``, ``axisym3d_a54_normal``: the loose ``hcell3d-axisym`` cell (same spheres) on
  the undrained triaxial path: isotropic rows of 1e-4 to 0.1 %, then the isochoric rows of the
  macro axial strain 2e-4 as the axisymmetric kinematics hand them to a cell whose axis lies along
  the loading axis (175 rows: its contacts open from the 162nd) or normal to it with t1 along it
  (400 rows); ``axisymmetric`` is the mapping of ``homogenization.material.orientation.AXISYMMETRIC_MAP``.
The YADE settings are the slow, accurate ones of the 2D reference (dt = 0.2 sqrt(m/kn), damping
0.5, 2.5e-7 strain per substep, unbalanced ratio 1e-6).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_reference import regenerate, run_yade, write_path  # noqa: E402 (tests/yade is not a package)

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE.parent / "data" / "yade3d"
SCRIPT = HERE / "cell3d_paths.py"
RADIUS = 0.5
"""Sphere radius of the reference cells [m]."""
YADE_SETTINGS = {"density": 2650.0, "dt_factor": 0.2, "damping": 0.5, "strain_per_substep": 2.5e-7,
                 "force_tolerance": 1e-6, "max_substeps": 200000, "contact_tolerance": 1e-9}
"""DEM settings of the YADE runs."""
CONTACT_LAW = {"kn": 2e8, "kt_over_kn": 0.5, "phi_g_deg": 30.0}
"""Contact law of the YADE runs (the package defaults)."""


@dataclass(frozen=True)
class Case:
    """One reference case: an initial opening angle and a strain path."""

    alpha0_deg: float
    """Initial opening angle [deg]."""
    segments: tuple[tuple[tuple[float, float, float], int], ...]
    """Path as ((d_eps_n, d_eps_t1, d_eps_t2), n_rows) segments [-], compression positive."""

    def path(self) -> np.ndarray:
        """Strain increments [-], shape (n_increments, 3)."""
        return np.concatenate([np.tile(step, (n, 1)) for step, n in self.segments])


def ten_sphere_cell(alpha0_deg: float, radius: float = RADIUS) -> dict:
    """The touching ten-sphere H-cell: radii, centres (n, t1, t2), driven mask, cell size (JSON-ready)."""
    a = math.radians(alpha0_deg)
    diameter = 2.0 * radius
    top, side = 0.5 * diameter + diameter * math.cos(a), diameter * math.sin(a)
    half = 0.5 * diameter
    position = [[top, 0, 0], [half, -side, 0], [-half, -side, 0], [-top, 0, 0], [-half, side, 0], [half, side, 0],
                [half, 0, -side], [-half, 0, -side], [-half, 0, side], [half, 0, side]]
    driven = [[True, True, True]] + [[False, True, True]] * 2 + [[True, True, True]] + [[False, True, True]] * 6
    return {"radius": [radius] * 10, "position": position, "driven": driven,
            "cell_size": [2.0 * top, 2.0 * side, 2.0 * side]}


def _load_unload(axis: int, alpha0_deg: float) -> Case:
    step = [0.0, 0.0, 0.0]
    step[axis] = 1e-4
    back = [-v for v in step]
    return Case(alpha0_deg, ((tuple(step), 100), (tuple(back), 60), (tuple(step), 80)))


def isochoric(d_axial: float) -> tuple[float, float, float]:
    """(d_eps_n, d_eps_t, d_eps_t) with (1 - d_eps_n)(1 - d_eps_t)^2 = 1 exactly."""
    lateral = 1.0 - 1.0 / math.sqrt(1.0 - d_axial)
    return (d_axial, lateral, lateral)


def axisymmetric(step: tuple[float, float, float]) -> tuple[float, float, float]:
    """Cell strains of the axisymmetric kinematics: with lat = (t1 + t2)/2 and c = (n - lat)/6,
    (n - c, lat - c, lat - c) [-]."""
    n, t1, t2 = step
    lat = 0.5 * (t1 + t2)
    c = (n - lat) / 6.0
    return (n - c, lat - c, lat - c)


_LATERAL = 1.0 - 1.0 / math.sqrt(1.0 - 2e-4)
CASES: dict[str, Case] = {
    "axial3d_a55": _load_unload(0, 55.0),
    "axial3d_a50": _load_unload(0, 50.0),
    "lateral3d_a55": _load_unload(1, 55.0),
    "lateral3d_a50": _load_unload(1, 50.0),
    "cv3d_a55": Case(55.0, (((1e-4, 1e-4, 1e-4), 10), (isochoric(2e-4), 500))),
    "axisym3d_a54_axial": Case(54.0, (((1e-4, 1e-4, 1e-4), 10), (axisymmetric(isochoric(2e-4)), 175))),
    "axisym3d_a54_normal": Case(54.0, (((1e-4, 1e-4, 1e-4), 10), (axisymmetric((_LATERAL, 2e-4, _LATERAL)), 400))),
}
"""Reference cases by name."""


def write_inputs(case: Case, prefix: Path, contact_law: dict, dem_settings: dict) -> Path:
    """Write the cell, settings and path files of ``case`` under ``prefix`` (its folder created) with
    ``contact_law`` and the YADE settings ``dem_settings``; return the prefix."""
    prefix.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{prefix}.cell.json").write_text(json.dumps(ten_sphere_cell(case.alpha0_deg)) + "\n")
    Path(f"{prefix}.settings.json").write_text(json.dumps({"contact_law": contact_law, "dem": dem_settings}) + "\n")
    write_path(case.path(), Path(f"{prefix}.path.csv"))
    return prefix


def run_case(prefix: Path, yade: str = "yade") -> Path:
    """Run YADE (``SCRIPT``) on the input files under ``prefix``; return the output prefix."""
    command = [yade, "-j1", "-n", "-x", str(SCRIPT), "--cell", f"{prefix}.cell.json", "--path", f"{prefix}.path.csv",
               "--settings", f"{prefix}.settings.json", "--out", str(prefix)]
    return run_yade(command, prefix.parent, prefix)


def write_case(name: str, out_dir: Path) -> Path:
    """Write the cell, path and settings files of case ``name``; return the output prefix."""
    return write_inputs(CASES[name], out_dir / name, CONTACT_LAW, YADE_SETTINGS)


def generate(name: str, out_dir: Path, yade: str = "yade") -> Path:
    """Write the inputs of ``name`` and run YADE on them in ``out_dir``; return the output prefix."""
    return run_case(write_case(name, out_dir), yade)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    return regenerate(argv, "Regenerate the YADE reference cases of the ten-sphere H-cell.", DATA_DIR, CASES, generate)


if __name__ == "__main__":
    sys.exit(main())
