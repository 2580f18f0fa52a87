"""Run: python tests/yade/make_reference3d_sand.py [--out tests/data/yade3d_sand] [--case NAME ...]

YADE references of the cell of the kind ``hcell3d-sand`` (the ten-sphere H-cell, linear contact law,
driven by the "amplified" kinematics), written like those of ``make_reference3d.py`` (the cell, path
and settings files, then tests/yade/cell3d_paths.py under ``yade``, producing ``<case>.yade.csv`` and
``<case>.json``) with the same contact law and YADE settings. ``CASES`` is the single definition of the
cases, also used by tests/test_yade_reference3d_sand.py.

Every case starts with isotropic rows of 1e-4 to 0.1 %, then follows the undrained triaxial path in
macro rows of axial strain 2e-4 (lateral strains 1 - 1/sqrt(1 - 2e-4)) as the amplified kinematics
(``amplified``: the cell's axisymmetric deviator times the gain, each plane two thirds of the volumetric
strain) hand them to one cell, written here without the package:
- ``sand3d_a54_axial``: loose (54 deg), the cell axis along the loading axis (opening, its contacts
  open before 15 %);
- ``sand3d_a54_normal``: loose, the axis normal to the loading axis with t1 along it (closing, sliding);
- ``sand3d_a49_normal``: dense (49 deg), axis normal (closing; the two planes' lateral grains meet);
- ``sand3d_g3_a52_normal``: the gain 3 at 52 deg, axis normal (the planes meet inside the window);
- ``sand3d_apart_g35_a52_normal``: the gain 3.5 at 52 deg, axis normal, the planes decoupled (YADE body
  masks: no interaction between the lateral grains of the two planes, the closed form's hypothesis).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_reference import regenerate  # noqa: E402 (tests/yade is not a package)
from make_reference3d import CONTACT_LAW, YADE_SETTINGS, Case, isochoric, run_case, write_inputs  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE.parent / "data" / "yade3d_sand"
GAIN = 2.0
"""Deviator gain of the amplified kinematics of ``hcell3d-sand`` [-]."""
MACRO_STEP = 2e-4
"""Macro axial strain per row of the undrained stage [-]."""


def amplified(step: tuple[float, float, float], gain: float = GAIN) -> tuple[float, float, float]:
    """Cell strains of the amplified kinematics [-]: with v = n + t1 + t2 and dev = n - (t1 + t2)/2,
    (v/3 + gain dev/2, v/3 - gain dev/2, v/3 - gain dev/2) (each plane (n, t_i) takes 2 v / 3)."""
    n, t1, t2 = step
    v, dev = n + t1 + t2, n - 0.5 * (t1 + t2)
    return (v / 3.0 + 0.5 * gain * dev, v / 3.0 - 0.5 * gain * dev, v / 3.0 - 0.5 * gain * dev)


@dataclass(frozen=True)
class SandCase(Case):
    """A case of the amplified kinematics: the cell's axis and the gain that made its path."""

    axis: str = "axial"
    """"axial": the cell axis n along the loading axis; "normal": n normal to it, t1 along it."""
    gain: float = GAIN
    """Deviator gain of the kinematics [-]."""
    apart: bool = False
    """The planes decoupled: no interaction between a lateral grain of plane A (2, 3, 5, 6) and one of
    plane B (7-10) (YADE body masks ``APART_MASK``)."""

    def macro_step(self) -> tuple[float, float, float]:
        """Normal strains (n, t1, t2) [-] of one undrained macro row along the cell axes, before the map."""
        axial, lateral, _ = isochoric(MACRO_STEP)
        return (axial, lateral, lateral) if self.axis == "axial" else (lateral, axial, lateral)


ISOTROPIC = ((1e-4, 1e-4, 1e-4), 10)
"""The isotropic rows that start every case."""


APART_MASK = (3, 1, 1, 3, 1, 1, 2, 2, 2, 2)
"""YADE body mask of grains 1-10 in a case with decoupled planes: the axial grains meet both planes."""


def undrained(alpha0_deg: float, axis: str, n_rows: int, gain: float = GAIN, apart: bool = False) -> SandCase:
    """The case of a cell with its axis along ("axial") or normal to ("normal", t1 along) the loading
    axis on the undrained triaxial path to ``n_rows`` macro rows of ``MACRO_STEP``."""
    macro = SandCase(alpha0_deg, (), axis, gain).macro_step()
    return SandCase(alpha0_deg, (ISOTROPIC, (amplified(macro, gain), n_rows)), axis, gain, apart)


CASES: dict[str, SandCase] = {
    "sand3d_a54_axial": undrained(54.0, "axial", 100),
    "sand3d_a54_normal": undrained(54.0, "normal", 300),
    "sand3d_a49_axial": undrained(49.0, "axial", 450),
    "sand3d_a49_normal": undrained(49.0, "normal", 500),
    "sand3d_g3_a52_normal": undrained(52.0, "normal", 600, gain=3.0),
    "sand3d_apart_g35_a52_normal": undrained(52.0, "normal", 450, gain=3.5, apart=True),
}
"""Reference cases by name."""


def write_case(name: str, out_dir: Path) -> Path:
    """Write the cell, path and settings files of case ``name``; return the output prefix."""
    prefix = write_inputs(CASES[name], out_dir / name, CONTACT_LAW, YADE_SETTINGS)
    if CASES[name].apart:
        cell_file = Path(f"{prefix}.cell.json")
        cell_file.write_text(json.dumps({**json.loads(cell_file.read_text()), "mask": list(APART_MASK)}) + "\n")
    return prefix


def generate(name: str, out_dir: Path, yade: str = "yade") -> Path:
    """Write the inputs of ``name`` and run YADE on them in ``out_dir``; return the output prefix."""
    return run_case(write_case(name, out_dir), yade)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    return regenerate(argv, "Regenerate the YADE reference cases of the hcell3d-sand cell.", DATA_DIR, CASES, generate)


if __name__ == "__main__":
    sys.exit(main())
