"""Run: python tests/yade/make_reference.py [--out tests/data/yade] [--case NAME ...]

Writes the strain path of every YADE reference case (``<case>.path.csv``) and runs
tests/yade/hcell_paths.py on it with ``yade`` (must be on PATH), producing
``<case>.yade.csv`` and ``<case>.json`` next to it. ``CASES`` is the single definition of the
cases, also used by tests/test_yade_reference.py.

Cases (cell strain increments d_eps_n, d_eps_t [-], compression positive):
- ``axial_a55``, ``axial_a40``: axial compression at constant width (d_eps_t = 0) to 1 %,
  partial unloading to 0.4 %, reloading to 1.2 %, rows of 1e-4;
- ``lateral_a55``, ``lateral_a40``: the same with the roles of n and t swapped (constant
  length);
- ``cv_a55_p585_theta0``, ``cv_a55_p585_theta90``: isotropic compression to eps_iso = 0.026
  (p0 = 5.85e6 N/m state of docs/model.md, "Reference response", rows of 2e-4), then constant volume
  for the cell at theta = 0 (+2e-4, -2e-4) or theta = 90 deg (-2e-4, +2e-4) to 20 %;
- ``cv_a55_p2e5_theta0``, ``cv_a55_p2e5_theta90``: the same from eps_iso = 0.0009 (p0 = 2e5
  N/m, iso rows of 1e-4).
- ``reclose_a60_theta22``, ``reclose_a60_theta40``: a shear reversal after full opening at
  alpha0 = 60 deg = 90 - phi_g: isotropic rows of 1e-4 to 0.0009 (p0 ~ 2e5 N/m), then the cell
  at theta = 22.5 or 40 deg of the constant-volume biaxial test eps1 = +5 %, then -10 %, in
  macro rows of 5e-4 (cell rows (+-5e-4 cos 2 theta, -+5e-4 cos 2 theta)). Every contact opens
  on loading, the type-1 contacts close again on the reversal onto a friction-locked wedge
  (alpha just above 60 deg), which collapses when alpha passes 60 deg. Free grains without
  force are held at rest (``--rest-unloaded``), so that the open rows keep y2 as the closed form
  does and the contacts close again from a defined state.
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE.parent / "data" / "yade"
SCRIPT = HERE / "hcell_paths.py"


@dataclass(frozen=True)
class Case:
    """One reference case: an initial opening angle and a strain path."""

    alpha0_deg: float
    """Initial opening angle [deg]."""
    segments: tuple[tuple[float, float, int], ...]
    """Path as (d_eps_n, d_eps_t, n_rows) segments [-], compression positive."""
    rest_unloaded: bool = False
    """Hold free grains without force at rest (hcell_paths.py ``--rest-unloaded``)."""

    def path(self) -> np.ndarray:
        """Strain increments [-], shape (n_increments, 2), columns (d_eps_n, d_eps_t)."""
        return np.concatenate([np.tile([d_n, d_t], (n, 1)) for d_n, d_t, n in self.segments])


def _load_unload(axis: int, alpha0_deg: float) -> Case:
    """Compression along ``axis`` (0 = n, 1 = t) to 1 %, unloading to 0.4 %, reloading to 1.2 %."""
    step = np.zeros(2)
    step[axis] = 1e-4
    return Case(alpha0_deg, ((step[0], step[1], 100), (-step[0], -step[1], 60), (step[0], step[1], 80)))


def _constant_volume(eps_iso: float, iso_row: float, sign: float) -> Case:
    """Isotropic rows of ``iso_row`` to ``eps_iso``, then (+-2e-4, -+2e-4) rows to 20 %."""
    n_iso = round(eps_iso / iso_row)
    return Case(55.0, ((iso_row, iso_row, n_iso), (sign * 2e-4, -sign * 2e-4, 1000)))


def _reversal_after_opening(theta_deg: float) -> Case:
    """alpha0 = 60 deg: isotropic rows of 1e-4 to 0.0009, then the cell at ``theta_deg`` of the
    constant-volume test eps1 = +5 % then -10 % in macro rows of 5e-4 (d_eps_n = d_eps11 cos^2 +
    d_eps22 sin^2 = d_eps11 cos 2 theta)."""
    row = 5e-4 * math.cos(math.radians(2.0 * theta_deg))
    return Case(60.0, ((1e-4, 1e-4, 9), (row, -row, 100), (-row, row, 200)), rest_unloaded=True)


CASES: dict[str, Case] = {
    "axial_a55": _load_unload(0, 55.0),
    "axial_a40": _load_unload(0, 40.0),
    "lateral_a55": _load_unload(1, 55.0),
    "lateral_a40": _load_unload(1, 40.0),
    "cv_a55_p585_theta0": _constant_volume(0.026, 2e-4, +1.0),
    "cv_a55_p585_theta90": _constant_volume(0.026, 2e-4, -1.0),
    "cv_a55_p2e5_theta0": _constant_volume(0.0009, 1e-4, +1.0),
    "cv_a55_p2e5_theta90": _constant_volume(0.0009, 1e-4, -1.0),
    "reclose_a60_theta22": _reversal_after_opening(22.5),
    "reclose_a60_theta40": _reversal_after_opening(40.0),
}
"""Reference cases by name."""


def write_path(path: np.ndarray, file: Path) -> None:
    """Write ``path`` (n_increments, 2 or 3) as CSV with header ``d_eps_n,d_eps_t`` (plane) or
    ``d_eps_n,d_eps_t1,d_eps_t2`` (space), every value exactly (``repr``, no negative zero)."""
    with open(file, "w") as handle:
        handle.write(("d_eps_n,d_eps_t" if path.shape[1] == 2 else "d_eps_n,d_eps_t1,d_eps_t2") + "\n")
        for row in path:
            handle.write(",".join(repr(float(v) + 0.0) for v in row) + "\n")


def run_yade(command: list[str], out_dir: Path, prefix: Path) -> Path:
    """Run the YADE ``command`` in ``out_dir``; RuntimeError unless it wrote ``<prefix>.yade.csv``."""
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=out_dir)
    if not Path(f"{prefix}.yade.csv").is_file():
        raise RuntimeError(f"yade wrote no {prefix}.yade.csv")
    return prefix


def generate(name: str, out_dir: Path, yade: str = "yade") -> Path:
    """Write ``<name>.path.csv`` and run YADE on it in ``out_dir``; return the output prefix."""
    case = CASES[name]
    out_dir.mkdir(parents=True, exist_ok=True)
    path_file = out_dir / f"{name}.path.csv"
    write_path(case.path(), path_file)
    prefix = out_dir / name
    command = [yade, "-j1", "-n", "-x", str(SCRIPT), "--path", str(path_file)]
    command += ["--alpha0-deg", f"{case.alpha0_deg:g}", "--out", str(prefix)]
    command += ["--rest-unloaded"] if case.rest_unloaded else []
    return run_yade(command, out_dir, prefix)


def regenerate(argv: list[str] | None, description: str, data_dir: Path, cases: dict,
               generate_case: Callable[[str, Path], Path]) -> int:
    """The command of a reference generator: --out (default ``data_dir``) and --case (names of
    ``cases``, default all) through ``generate_case(name, out_dir)``; exit code 2 without yade."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", type=Path, default=data_dir, help="output folder")
    parser.add_argument("--case", choices=sorted(cases), action="append", help="case to run (repeatable; default all)")
    args = parser.parse_args(argv)
    if shutil.which("yade") is None:
        print("error: yade is not on PATH", file=sys.stderr)
        return 2
    for name in args.case or cases:
        print(generate_case(name, args.out))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    return regenerate(argv, "Regenerate the YADE reference cases of the six-disk H-cell.", DATA_DIR, CASES, generate)


if __name__ == "__main__":
    sys.exit(main())
