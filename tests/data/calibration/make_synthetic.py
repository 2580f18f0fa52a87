"""Make the synthetic "measured" curves of the calibration tests and benchmark.

python tests/data/calibration/make_synthetic.py [--out tests/data/calibration]

Runs the meso-DEM backend (``python -m homogenization.biaxial --backend dem``) at the
parameter values ``TRUTH``, which the calibration is not told, for an undrained test
(q and p) and a drained test (q and eps_v), samples each curve at ``N_POINTS`` axial strains
and adds Gaussian noise of ``NOISE`` x the channel's largest abs value (seeded). Writes
undrained.csv, drained.csv and truth.json (the values, read only by the benchmark to score
the posterior). Units of the package's curve.csv: N/m, strains [-], compression positive.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

TRUTH = {"phi_g": 26.0, "kn": 3.0e8, "kt_over_kn": 0.6, "alpha0": 58.0}
"""Parameters of the DEM runs: phi_g [deg], kn [N/m], kt_over_kn [-], alpha0 [deg]."""
TESTS = {"undrained": (5.85e6, ("q", "p")), "drained": (3.0e6, ("q", "eps_v"))}
"""Test -> (p0 [N/m], channels written)."""
EPS_MAX = 0.05
"""Largest axial strain [-]."""
N_POINTS = 25
"""Measured points per curve [-]."""
NOISE = 0.02
"""Standard deviation of the noise as a fraction of each channel's largest abs value [-]."""
DEM = ("--orientations", "72", "--increment", "1e-4", "--iso-increment", "1e-4", "--threads", "2")
"""DEM settings: a finer increment and more orientations than the calibration's forward model."""
SEED = 20


def dem_curve(test: str, p0: float, work: Path) -> dict[str, np.ndarray]:
    """eps1, q, p, eps_v [-, N/m, N/m, -] of the shear stage of one DEM run, from the end of stage 1."""
    out = work / test
    command = [sys.executable, "-m", "homogenization.biaxial", "--backend", "dem", "-q", "--p0", f"{p0:g}",
               "--eps-max", f"{EPS_MAX:g}", "--alpha0", f"{TRUTH['alpha0']:g}", "--phi", f"{TRUTH['phi_g']:g}",
               "--kn", f"{TRUTH['kn']:g}", "--kt", f"{TRUTH['kt_over_kn'] * TRUTH['kn']:g}", *DEM, "--out", str(out)]
    if test == "drained":
        command.append("--drained")
    subprocess.run(command, check=True)
    curve = np.genfromtxt(out / "curve.csv", delimiter=",", names=True, dtype=None, encoding=None)
    shear = np.flatnonzero(curve["stage"] == "shear")
    rows = np.concatenate([[shear[0] - 1], shear])
    e11, e22 = curve["eps11"][rows], curve["eps22"][rows]
    return {"eps1": e11 - e11[0], "q": curve["q"][rows], "p": curve["p"][rows],
            "eps_v": (e11 + e22) - (e11[0] + e22[0])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args()
    rng = np.random.default_rng(SEED)
    eps1 = np.linspace(EPS_MAX / N_POINTS, EPS_MAX, N_POINTS)
    with tempfile.TemporaryDirectory() as work:
        for test, (p0, channels) in TESTS.items():
            curve = dem_curve(test, p0, Path(work))
            columns = [eps1]
            for c in channels:
                clean = np.interp(eps1, curve["eps1"], curve[c])
                columns.append(clean + NOISE * np.max(np.abs(clean)) * rng.standard_normal(N_POINTS))
            lines = [f"# test = {test}", f"# p0 = {p0:g}",
                     f"# synthetic: DEM ({' '.join(DEM)}) + {NOISE:.0%} noise, tests/data/calibration/make_synthetic.py",
                     ",".join(("eps1", *channels))]
            lines += [",".join(f"{v:.9g}" for v in row) for row in np.stack(columns, axis=1)]
            (args.out / f"{test}.csv").write_text("\n".join(lines) + "\n")
    (args.out / "truth.json").write_text(json.dumps(TRUTH, indent=2) + "\n")


if __name__ == "__main__":
    main()
