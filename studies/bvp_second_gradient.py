"""python studies/bvp_second_gradient.py [--meshes 8,16 16,32 32,64] [--length 0.02] [--orientations 24] [--run]

Shear band of the dense specimen with its weak zone (alpha0 = 40 deg, weak zone alpha0 = 50 deg,
p0 = 2e5 N/m, shear to 10 % at 1e-3, closed form) on several meshes, plain first-gradient
solver and local second gradient (``hmodel bvp --length``) side by side. With --run the runs
are made (``python -m homogenization.bvp``, outputs in studies/results/bvp_second_gradient/);
then every run folder there is analysed:

- curve: peak q/p0 and its eps1, q/p0 at 2 % past the peak (eps1 = peak + 0.02), Newton
  iterations per shear step;
- band: ``homogenization.fe.band.measure_band`` on the deviatoric-strain increment of the
  last --window (2 %) before --eps1-end where only the branch rising from the weak zone passes
  (``REGION``; bins of half the finest element), width and angle from x;
- predictions: the material point (drained biaxial, same settings) gives the friction angle at
  its peak, sin phi = q / (2 p), and the dilatancy angle there, sin psi = -d eps_v / d gamma
  (gamma = eps1 - eps2); Coulomb 45 + phi/2, Roscoe 45 + psi/2, Arthur 45 + (phi + psi)/4 [deg].

--eps1-end E analyses every run up to the shear strain E (a run still going is read from its
checkpoint). Writes studies/results/bvp_second_gradient/[TAG/]summary.json, profiles.png and fields.png
(--tag TAG: runs and outputs in that subfolder; --no-plain: the second-gradient runs only).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
from matplotlib.figure import Figure

from homogenization.backends import make_cell_model
from homogenization.element_test import driver, programme as programmes
from homogenization.fe import solver as fe
from homogenization.fe.band import measure_band
from warp_hcell.mesostructures.hcell import h_cell

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "studies" / "results" / "bvp_second_gradient"
P0, ALPHA0, F, EPS_MAX, INCREMENT = 2e5, 40.0, 0.2, 0.10, 1e-3
def REGION(x: np.ndarray) -> np.ndarray:
    """Where the band is measured: x <= 0.6 m, y >= H/2, more than 0.3 m from the weak zone's
    centre (0, H/2): the branch rising from the weak zone crosses it alone (the bands reflect at
    the faces and platens), and the weak zone itself is left out."""
    return (x[:, 0] <= 0.6) & (x[:, 1] >= 1.0) & (np.hypot(x[:, 0], x[:, 1] - 1.0) > 0.3)


BAND_WINDOW = 0.02
"""Default strain window before --eps1-end whose deviatoric-strain increment locates the band [-]."""


def run_case(nx: int, ny: int, length: float | None, orientations: int, folder: Path = OUT) -> Path:
    name = f"{nx}x{ny}_" + ("plain" if length is None else f"L{length:g}")
    out = folder / name
    argv = [sys.executable, "-m", "homogenization.bvp", "--alpha0", str(ALPHA0), "--p0", str(P0),
            "--eps-max", str(EPS_MAX), "--increment", str(INCREMENT), "--orientations", str(orientations),
            "--elements", f"{nx},{ny}", "--imperfection", str(F), "--iso-steps", "20", "--checkpoint-every", "10",
            "--out", str(out)]
    if length is not None:
        argv += ["--length", str(length)]
    if (out / "checkpoint.h5").exists() and not (out / "curve.csv").exists():
        argv.append("--resume")
    elif out.exists():
        argv.append("--overwrite")
    start = time.perf_counter()
    subprocess.run(argv, check=True, cwd=ROOT)
    (out / "wall.txt").write_text(f"{time.perf_counter() - start:.1f}\n")
    return out


FIELDS: dict[str, tuple[np.ndarray, np.ndarray]] = {}
"""Gauss points and band-window deviatoric-strain increment of each analysed run (for the figure)."""


def load_run(folder: Path) -> dict:
    """History and fields of a run folder: from run.h5, or from checkpoint.h5 of a run still going."""
    if (folder / "run.h5").exists():
        with h5py.File(folder / "run.h5") as f:
            return {"parameters": json.loads(f.attrs["parameters"]), "stage": f["history/stage"].asstr()[()],
                    "eps11": f["history/eps11"][()], "q": f["history/q"][()],
                    "iterations": f["history/iterations"][()], "strain": f["fields/strain"][()],
                    "points": f["mesh/gauss_points"][()], "weights": f["mesh/gauss_weights"][()], "complete": True}
    with h5py.File(folder / "checkpoint.h5") as f:
        parameters = json.loads(f.attrs["parameters"])
        res = f["results"]
        run = {"parameters": parameters, "stage": res["stage"].asstr()[()], "eps11": res["eps11"][()],
               "q": res["sigma11"][()] - res["sigma22"][()], "iterations": res["iterations"][()],
               "strain": res["strain"][()], "complete": False}
    specimen = fe.BiaxialSpecimen(*parameters["elements"])
    run["points"] = np.asarray(specimen.basis.global_coordinates()).reshape(2, -1).T
    run["weights"] = specimen.weights
    return run


def analyse(folder: Path, bin_width: float, eps1_end: float, window: float) -> dict:
    run = load_run(folder)
    parameters, stage, eps11, q = run["parameters"], run["stage"], run["eps11"], run["q"]
    iterations, strain, points, weights = run["iterations"], run["strain"], run["points"], run["weights"]
    start = int(np.flatnonzero(stage == "shear")[0]) - 1
    last = int(np.searchsorted(eps11 - eps11[start], eps1_end + 1e-9))  # steps up to eps1_end
    stage, eps11, q, iterations, strain = stage[:last], eps11[:last], q[:last], iterations[:last], strain[:last]
    shear = np.flatnonzero(stage == "shear")
    start = shear[0] - 1
    e1 = eps11 - eps11[start]
    peak = int(np.argmax(q))
    after = float(np.interp(e1[peak] + 0.02, e1[shear], q[shear]))
    first = int(np.searchsorted(e1, e1[-1] - window - 1e-9))
    increment = strain[-1] - strain[first]
    eps_d = np.hypot(increment[:, 0] - increment[:, 1], increment[:, 2])
    try:
        band = measure_band(points, weights, eps_d, bin_width=bin_width, region=REGION(points))
        width, angle, profile = band.width, band.angle_deg, (band.profile_s.tolist(), band.profile.tolist())
    except ValueError as exc:
        width, angle, profile = float("nan"), float("nan"), str(exc)
    wall = (folder / "wall.txt").read_text().strip() if (folder / "wall.txt").exists() else None
    FIELDS[folder.name] = (points, eps_d)
    return {"case": folder.name, "complete": run["complete"], "eps1_end": float(e1[-1]), "elements": parameters["elements"], "length": parameters.get("length"),
            "second_gradient_modulus": parameters.get("second_gradient_modulus"),
            "reference_modulus": parameters.get("reference_modulus"),
            "peak_q_over_p0": float(q[peak] / P0), "peak_eps1": float(e1[peak]),
            "q_over_p0_2pc_past_peak": after / P0, "final_q_over_p0": float(q[-1] / P0),
            "band_width_m": width, "band_angle_deg": angle, "profile": profile,
            "shear_iterations_mean": float(iterations[shear].mean()), "shear_iterations_max": int(iterations[shear].max()),
            "wall_s": None if wall is None else float(wall),
            "curve": {"eps1": e1[shear].tolist(), "q_over_p0": (q[shear] / P0).tolist()}}


def predictions(orientations: int) -> dict:
    """Friction and dilatancy angles of the material point at its peak, and the three band angles [deg]."""
    record = driver.run(make_cell_model("analytical"), programmes.biaxial(P0, EPS_MAX, INCREMENT, drained=True),
                        mesostructure=h_cell(ALPHA0), n_orientations=orientations, progress=False)
    shear = np.flatnonzero(record.stage == "shear")
    q, p = record.q[shear], record.p[shear]
    k = int(np.argmax(q))
    phi = np.degrees(np.arcsin(q[k] / (2.0 * p[k])))
    e1, e2 = record.eps11[shear], record.eps22[shear]
    d_v, d_g = np.gradient(e1 + e2), np.gradient(e1 - e2)
    psi = np.degrees(np.arcsin(-d_v[k] / d_g[k]))
    return {"phi_deg": float(phi), "psi_deg": float(psi), "peak_q_over_p0": float(q[k] / P0),
            "coulomb_deg": 45.0 + phi / 2.0, "roscoe_deg": 45.0 + psi / 2.0, "arthur_deg": 45.0 + (phi + psi) / 4.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=["8,16", "16,32", "32,64"])
    parser.add_argument("--length", type=float, default=0.02)
    parser.add_argument("--orientations", type=int, default=24)
    parser.add_argument("--run", action="store_true")
    parser.add_argument("--no-plain", action="store_true", help="with --run: the second-gradient runs only")
    parser.add_argument("--tag", default="", help="runs and outputs in studies/results/bvp_second_gradient/TAG/")
    parser.add_argument("--window", type=float, default=BAND_WINDOW, help="band window [-]")
    parser.add_argument("--eps1-end", type=float, default=EPS_MAX,
                        help="analyse every run up to this shear strain (runs still going: their checkpoint)")
    args = parser.parse_args()
    meshes = [tuple(int(v) for v in m.split(",")) for m in args.meshes]
    out = OUT / args.tag
    if args.run:
        for nx, ny in meshes:
            for length in (args.length,) if args.no_plain else (None, args.length):
                run_case(nx, ny, length, args.orientations, out)
    finest = max(nx for nx, _ in meshes)
    folders = [folder for folder in sorted(out.iterdir())
               if (folder / "run.h5").exists() or (folder / "checkpoint.h5").exists()]
    rows = [analyse(folder, 0.5 / finest, args.eps1_end, args.window) for folder in folders]
    summary = {"eps1_end": args.eps1_end, "p0": P0, "alpha0": ALPHA0, "imperfection": F, "orientations": args.orientations,
               "band_window": args.window, "predictions": predictions(args.orientations), "runs": rows}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print("case | complete | eps1 end | peak q/p0 (eps1) | q/p0 at peak + 2 % | q/p0 at eps1 end | band width [m] | angle [deg] | its/step mean, max | wall [s]")
    for r in rows:
        print(f"{r['case']} | {r['complete']} | {100 * r['eps1_end']:.1f} % | {r['peak_q_over_p0']:.4f} ({100 * r['peak_eps1']:.1f} %) | {r['q_over_p0_2pc_past_peak']:.4f} | "
              f"{r['final_q_over_p0']:.4f} | {r['band_width_m']:.4f} | {r['band_angle_deg']:.1f} | "
              f"{r['shear_iterations_mean']:.2f}, {r['shear_iterations_max']} | {r['wall_s']}")
    print("predictions:", json.dumps(summary["predictions"]))
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax_q, ax_p = fig.subplots(1, 2)
    for r in rows:
        style = "-" if r["length"] else "--"
        ax_q.plot(100 * np.array(r["curve"]["eps1"]), r["curve"]["q_over_p0"], style, label=r["case"])
        if isinstance(r["profile"], list):
            s, v = np.array(r["profile"][0]), np.array(r["profile"][1])
            ax_p.plot(s, v, style, label=r["case"])
    ax_q.set(xlabel="eps1 [%] (from the end of the isotropic stage)", ylabel="q / p0", title="load-displacement")
    ax_p.set(xlabel="distance across the band [m]", ylabel="deviatoric strain increment in the window [-]",
             title="profile across the band")
    ax_q.legend(fontsize=7)
    ax_p.legend(fontsize=7)
    fig.savefig(out / "profiles.png", dpi=110)
    fig = Figure(figsize=(2.2 * len(FIELDS), 4.2), layout="constrained")
    for ax, (name, (xy, value)) in zip(np.atleast_1d(fig.subplots(1, len(FIELDS))), sorted(FIELDS.items())):
        dots = ax.scatter(xy[:, 0], xy[:, 1], c=value, s=2.0 if len(value) > 4000 else 5.0, cmap="viridis")
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=6)
        fig.colorbar(dots, ax=ax, shrink=0.6).ax.tick_params(labelsize=6)
    fig.suptitle(f"deviatoric strain increment over the last {100 * args.window:.0f} % before eps1 = "
                 f"{100 * args.eps1_end:.1f} %", fontsize=9)
    fig.savefig(out / "fields.png", dpi=110)


if __name__ == "__main__":
    main()
