"""python studies/bench_hertz_strain_to_peak.py [--alpha0 54.5] [--phi 35.6] [--kn 1.79e7] [--kt-over-kn 1.07]
[--shear-modulus 1.4e8] [--poisson 0.2] [--increment 2e-3] [--out runs/hertz_strain_to_peak]

How the strain to peak of the 3D H-model grows with the confining pressure under the linear and the
Hertz-Mindlin contact laws, beside the drained triaxial tests of Dobrany sand
(benchmarks/lab_data/dobrany_sand/, measured at 50, 100 and 200 kPa). Runs the calibration's own
forward model (``homogenization.calibration.forward.simulate``: the closed form on Lebedev order
11 x 4 aligned spins, drained, at the data's axial strains) for each law at each pressure and prints
the peak q / p0, the axial strain at the peak and where q first reaches half the peak, and the ratios
of those strains 200 kPa / 50 kPa, beside the data's. Forward fallbacks (drained Newton iterations
that ended above the stress tolerance; their last iterate is used) are counted per run.

The defaults are the linear law's posterior mean of an early short chain on the 50 and 200 kPa tests
(studies/results/real_sand_first_look.txt) and a Hertz-Mindlin law whose tangent normal stiffness at 100 kPa is near that kn
(G = 0.14 GPa: the H-cell's stiffness, not the mineral's); nu = 0.2 gives kt / kn = 2 (1 - nu) /
(2 - nu) = 0.89.

The forward model reads the linear law's parameters only; ``hertz_forward`` runs it on the
Hertz-Mindlin cells of ``Analytical3DCell.with_hertz_cell_laws`` (shear_modulus in the kn slot,
poisson in the kt_over_kn slot) for this measurement.

With --grid PHIS ALPHA0S LINEAR_KNS HERTZ_GS (comma lists) it instead fits each law on a grid:
every combination runs as one population of the forward model on the 50 and 200 kPa tests, the
set with the smallest RMS over both tests of RMS |dq| / q_peak is kept (q only; kt/kn and nu as
given), and its prediction of the 100 kPa test is scored the same way; then the table as above for
the best set of each law.

Writes the summary to --out/summary.json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import numpy as np

from homogenization.backends.analytical import Analytical3DCell
from homogenization.calibration import forward
from homogenization.calibration.data import read_test

DATA = Path(__file__).resolve().parents[1] / "benchmarks" / "lab_data" / "dobrany_sand"
TESTS = {50e3: "cid_50kpa.csv", 100e3: "cid_100kpa.csv", 200e3: "cid_200kpa.csv"}


@contextlib.contextmanager
def hertz_forward():
    """Within: the forward model's 3D cells are Hertz-Mindlin cells, with kn read as the grain shear
    modulus G [Pa] and kt_over_kn as the Poisson ratio nu [-]."""
    def with_hertz(cls, kn, kt_over_kn, phi_g_deg, radius, alpha0_deg=None, **options):
        return cls.with_hertz_cell_laws(kn, kt_over_kn, phi_g_deg, radius, alpha0_deg=alpha0_deg, **options)

    Analytical3DCell.with_cell_laws = classmethod(with_hertz)
    try:
        yield
    finally:
        del Analytical3DCell.with_cell_laws  # the inherited linear one again


def peak(eps1: np.ndarray, q: np.ndarray) -> tuple[float, float, float]:
    """(q_peak [Pa], eps1 at the peak [-], eps1 where q first reaches half the peak [-])."""
    k = int(np.nanargmax(q))
    half = int(np.argmax(q >= 0.5 * q[k]))
    return float(q[k]), float(eps1[k]), float(eps1[half])


def add_ratios(rows: dict) -> None:
    """Add the ratios 200 kPa / 50 kPa of the strains at the peak and at half the peak to ``rows``."""
    for key, ratio in (("eps1_at_peak", "ratio_eps_peak_200_50"), ("eps1_at_half_peak", "ratio_eps_half_200_50")):
        rows[ratio] = rows["200000"][key] / rows["50000"][key]


def grid_fit(name: str, context, tests: dict, settings, grid: dict[str, np.ndarray], fixed: dict[str, float]) -> dict:
    """The best set of ``grid`` (phi_g, alpha0 and kn values; every combination) on the 50 and 200 kPa
    tests, its score and its prediction of the 100 kPa test (module docstring)."""
    mesh = np.meshgrid(*grid.values(), indexing="ij")
    params = {key: m.ravel() for key, m in zip(grid, mesh)}
    params.update({key: np.full(mesh[0].size, value) for key, value in fixed.items()})
    scores, curves = {}, {}
    with context(), np.errstate(all="ignore"):
        for p0, test in tests.items():
            run = forward.simulate(test, params, settings)
            qd = test.observed["q"]
            scores[p0] = np.sqrt(np.nanmean((run.q - qd) ** 2, axis=1)) / qd.max()
            curves[p0] = run
    fit = np.sqrt((scores[50e3] ** 2 + scores[200e3] ** 2) / 2.0)
    best = int(np.argmin(np.where(np.isfinite(fit), fit, np.inf)))
    print(f"{name}: best of {fit.size} sets: " + ", ".join(f"{k} {v[best]:g}" for k, v in params.items())
          + f"; fit RMS |dq|/q_peak {fit[best]:.3f}, predicted 100 kPa {scores[100e3][best]:.3f}")
    rows = {"best": {k: float(v[best]) for k, v in params.items()}, "fit_rms_dq_over_qpeak": float(fit[best]),
            "predict_100kpa_rms_dq_over_qpeak": float(scores[100e3][best]), "n_sets": int(fit.size)}
    for p0, test in tests.items():
        q_peak, eps_peak, eps_half = peak(test.eps1, curves[p0].q[best])
        rows[f"{p0:g}"] = {"q_peak_over_p0": q_peak / p0, "eps1_at_peak": eps_peak, "eps1_at_half_peak": eps_half,
                           "forward_fallbacks": int(curves[p0].n_fallback[best])}
    add_ratios(rows)
    return rows


def floats(text: str) -> np.ndarray:
    """A comma list of numbers."""
    return np.array([float(v) for v in text.split(",")])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--alpha0", type=float, default=54.5, help="initial opening angle [deg]")
    parser.add_argument("--phi", type=float, default=35.6, help="inter-granular friction angle [deg]")
    parser.add_argument("--kn", type=float, default=1.79e7, help="linear law: normal stiffness [N/m]")
    parser.add_argument("--kt-over-kn", type=float, default=1.07, help="linear law: kt / kn [-]")
    parser.add_argument("--shear-modulus", type=float, default=1.4e8, help="Hertz-Mindlin: G [Pa]")
    parser.add_argument("--poisson", type=float, default=0.2, help="Hertz-Mindlin: nu [-]")
    parser.add_argument("--increment", type=float, default=2e-3, help="axial strain increment [-]")
    parser.add_argument("--grid", nargs=4, metavar=("PHIS", "ALPHA0S", "LINEAR_KNS", "HERTZ_GS"),
                        help="fit each law on this grid instead (comma lists; module docstring)")
    parser.add_argument("--out", type=Path, default=Path("runs/hertz_strain_to_peak"))
    args = parser.parse_args()
    settings = forward.ForwardSettings(increment=args.increment, iso_increment=args.increment / 2)
    laws = {"linear": ({"kn": args.kn, "kt_over_kn": args.kt_over_kn}, contextlib.nullcontext),
            "hertz-mindlin": ({"kn": args.shear_modulus, "kt_over_kn": args.poisson}, hertz_forward)}
    summary: dict[str, dict] = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    tests = {p0: read_test(DATA / file) for p0, file in TESTS.items()}
    for name, (values, context) in laws.items():
        if args.grid:
            phis, alpha0s, kns, shear_moduli = (floats(v) for v in args.grid)
            grid = {"phi_g": phis, "alpha0": alpha0s, "kn": kns if name == "linear" else shear_moduli}
            summary[name] = grid_fit(name, context, tests, settings, grid, {"kt_over_kn": values["kt_over_kn"]})
            continue
        rows = {}
        params = {"phi_g": np.array([args.phi]), "alpha0": np.array([args.alpha0]),
                  **{k: np.array([v]) for k, v in values.items()}}
        with context():
            for p0, test in tests.items():
                curves = forward.simulate(test, params, settings)
                q_peak, eps_peak, eps_half = peak(test.eps1, curves.q[0])
                rows[f"{p0:g}"] = {"q_peak_over_p0": q_peak / p0, "eps1_at_peak": eps_peak,
                                   "eps1_at_half_peak": eps_half, "forward_fallbacks": int(curves.n_fallback[0])}
        add_ratios(rows)
        summary[name] = rows
    data = {}
    for p0, test in tests.items():
        q_peak, eps_peak, eps_half = peak(test.eps1, test.observed["q"])
        data[f"{p0:g}"] = {"q_peak_over_p0": q_peak / p0, "eps1_at_peak": eps_peak, "eps1_at_half_peak": eps_half,
                           "forward_fallbacks": 0}
    add_ratios(data)
    summary["data"] = data
    print(f"{'':14s}" + "".join(f"{p / 1e3:>5g} kPa: q/p0 eps_pk eps_half fb " for p in TESTS) + " ratios 200/50: pk half")
    for name in ("linear", "hertz-mindlin", "data"):
        rows = summary[name]
        cells = "".join(f"{rows[f'{p:g}']['q_peak_over_p0']:>15.2f} {100 * rows[f'{p:g}']['eps1_at_peak']:5.2f}% "
                        f"{100 * rows[f'{p:g}']['eps1_at_half_peak']:6.3f}% {rows[f'{p:g}']['forward_fallbacks']:3d}"
                        for p in TESTS)
        print(f"{name:14s}{cells}  {rows['ratio_eps_peak_200_50']:10.2f} {rows['ratio_eps_half_200_50']:5.2f}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
