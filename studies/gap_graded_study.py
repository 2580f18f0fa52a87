"""python studies/gap_graded_study.py [--runs runs] [--figures docs/figures]

Tables and figures of docs/gap_graded.md from the sweep folders that the commands of that page
write (runs/gap_a50, runs/gap_a55, runs/gap_instability, runs/gap_erode_*, runs/gap_ann/sweep
for DEM vs ANN; a missing folder skips its table). Prints markdown
tables: the constant-volume response against the fine-grain size ratio (peak q/p0, eps1 at
the peak, p/p0 at 5, 10, 15 %, liquefaction = p/p0 < 0.2 at 15 %), the first q peaks of the
instability analysis with the slope of the line through the origin fitted to them, and the
erosion cases. Writes docs/figures/gap_*.png. Reads only summary.csv and the case run files.
Sign convention: compression positive; stresses N/m.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from homogenization.output import figures, io
from homogenization.cli import sweep
from homogenization.output.figure_style import apply_style, figure_legend, GRID, LABELS, number
from warp_hcell.mesostructures.builders import parse_mesostructure
from warp_hcell.mesostructures.hcell import pore_ratio

LIQUEFACTION = 0.2
"""p/p0 at eps1 = 15 % below which a sample is said to liquefy [-]."""
DEPARTURE = 1e-3
"""|p - p_plain| / p0 beyond which a fines cell is said to depart from the plain cell [-]
(eps1 = 0 for a grain already caught in the isotropic stage)."""


def fine_ratio(text: str) -> float:
    """Fine-grain radius over r of a spec (0 for the plain cell)."""
    ratio = dict(parse_mesostructure(text).options).get("ratio", (0.0,))
    return float(sum(ratio))


def curve(folder: Path, row: dict) -> figures.ShearCurve:
    return figures.shear_curve(io.read_run(folder / sweep.CASES_DIR / row["case"] / io.RUN_FILE).record)


def fines_table(runs: Path, figures: Path) -> None:
    print("| alpha0 | p0 [N/m] | r_f / r | r_f / pore | departs from plain at eps1 [%] | peak q/p0 | eps1 at peak [%] "
          "| first softening peak q/p0 | p/p0 at 5 % | 10 % | 15 % | min p/p0 | liquefies |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    fig = Figure(figsize=(12.0, 4.6), layout="constrained")
    ax_p, ax_q = fig.subplots(1, 2)
    for alpha0, name in ((50.0, "gap_a50"), (55.0, "gap_a55")):
        rows = sweep.read_summary(runs / name / sweep.SUMMARY_FILE)
        for p0 in sorted({r["p0"] for r in rows}):
            sel = sorted((r for r in rows if r["p0"] == p0), key=lambda r: fine_ratio(r["mesostructure"]))
            x = []
            plain = curve(runs / name, next(r for r in sel if r["mesostructure"] == "hcell"))
            for r in sel:
                ratio = fine_ratio(r["mesostructure"])
                x.append(ratio / pore_ratio(alpha0))
                fp = r["first_peak_q"] / p0
                c = curve(runs / name, r)
                apart = np.flatnonzero(np.abs(c.p - np.interp(c.eps1, plain.eps1, plain.p)) > DEPARTURE * p0)
                departs = "-" if apart.size == 0 else f"{100 * c.eps1[apart[0]]:.2f}"
                print(f"| {alpha0:g} | {p0:g} | {ratio:.4g} | {x[-1]:.3f} | {departs} | {r['peak_q'] / p0:.3f} | "
                      f"{100 * r['eps1_at_peak']:.2f} | {'-' if math.isnan(fp) else f'{fp:.3f}'} | "
                      f"{r['p_at_5pct'] / p0:.3f} | {r['p_at_10pct'] / p0:.3f} | {r['p_at_15pct'] / p0:.3f} | "
                      f"{c.p.min() / p0:.3f} | {'yes' if r['p_at_15pct'] / p0 < LIQUEFACTION else 'no'} |")
            label = f"$\\alpha_0$ = {alpha0:g}°, $p_0 = {number(p0)}$ N/m"
            ax_p.plot(x, [r["p_at_15pct"] / p0 for r in sel], "o-", label=label)
            ax_q.plot(x, [r["peak_q"] / p0 for r in sel], "o-", label=label)
    ax_p.axhline(LIQUEFACTION, color="0.5", ls=":", lw=1.0)
    ax_p.set(yscale="log", xlabel="fine-grain radius / pore inscribed radius [-]",
             ylabel=r"$p/p_0$ at $\varepsilon_1$ = 15 % [-]",
             title="end of the constant-volume test (dotted: liquefaction)")
    ax_q.set(yscale="log", xlabel="fine-grain radius / pore inscribed radius [-]", ylabel=r"peak $q/p_0$ [-]",
             title=r"largest deviator up to $\varepsilon_1$ = 15 %")
    for ax in (ax_p, ax_q):
        ax.grid(True, which="both", **GRID)
    figure_legend(fig, ax_p.get_lines())  # both panels draw the same cases
    figures.save_figure(apply_style(fig), figures / "gap_fines_ratio.png")

    fig = Figure(figsize=(12.0, 4.6), layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, (alpha0, name, p0) in zip(axes, ((55.0, "gap_a55", 2e5), (50.0, "gap_a50", 2e5))):
        rows = [r for r in sweep.read_summary(runs / name / sweep.SUMMARY_FILE) if r["p0"] == p0]
        rows.sort(key=lambda r: fine_ratio(r["mesostructure"]))
        colours = sweep.plotting_colours(len(rows))
        for colour, r in zip(colours, rows):
            c = curve(runs / name, r)
            ax.plot(100 * c.eps1, c.p / p0, color=colour, label=f"$r_f/r$ = {fine_ratio(r['mesostructure']):.4g}")
        ax.axhline(LIQUEFACTION, color="0.5", ls=":", lw=1.0)
        ax.set(yscale="log", xlabel=LABELS["eps1"], ylabel=LABELS["p/p0"],
               title=f"$\\alpha_0$ = {alpha0:g}°, $p_0 = {number(p0)}$ N/m")
        ax.grid(True, which="both", **GRID)
        ax.legend(fontsize=7)  # each panel its own cells
    figures.save_figure(apply_style(fig), figures / "gap_fines_curves_p2e5.png")


def instability_families(runs: Path) -> dict[str, tuple[Path, list[dict]]]:
    """Family label -> (sweep folder, rows): plain cell, one fine grain for every alpha0, 0.97 of each pore."""
    families: dict[str, tuple[Path, list[dict]]] = {}
    folder = runs / "gap_instability"
    for r in sweep.read_summary(folder / sweep.SUMMARY_FILE):
        label = "plain" if r["mesostructure"] == "hcell" else f"r_f/r = {fine_ratio(r['mesostructure']):g}"
        families.setdefault(label, (folder, []))[1].append(r)
    folder = runs / "gap_instability_pore97"
    if (folder / sweep.SUMMARY_FILE).is_file():
        families["r_f = 0.97 pore"] = (folder, sweep.read_summary(folder / sweep.SUMMARY_FILE))
    return families


def instability(runs: Path, figures: Path) -> None:
    families = instability_families(runs)
    print("\n| cell | p0 [N/m] | alpha0 | r_f / r | first peak q/p0 | p/p0 at it | eps1 at it [%] | q/p at it |")
    print("|---|---|---|---|---|---|---|---|")
    p0s = sorted({r["p0"] for _, rows in families.values() for r in rows})
    fig = Figure(figsize=(14.0, 5.5), layout="constrained")
    axes = dict(zip(p0s, fig.subplots(1, len(p0s))))
    styles = dict(zip(families, ("-", "--", ":", "-.")))
    markers = dict(zip(families, ("o", "s", "^", "v")))
    slopes = {}
    for family, (folder, rows) in families.items():
        for p0 in p0s:
            sel = sorted((r for r in rows if r["p0"] == p0), key=lambda r: r["alpha0"])
            ax = axes[p0]
            colours = sweep.plotting_colours(len(sel))
            peaks = []
            for colour, r in zip(colours, sel):
                c = curve(folder, r)
                ax.plot(c.p / p0, c.q / p0, color=colour, ls=styles[family], lw=0.8,
                        label=f"$\\alpha_0$ = {r['alpha0']:g}°" if family == "plain" else None)
                fp = r["first_peak_q"]
                if not math.isnan(fp):
                    point = (r["p_at_first_peak"] / p0, fp / p0)
                    if point[0] < 1.0:
                        peaks.append(point)
                    ax.plot(*point, markers[family], color=colour, ms=5, mfc=colour if point[0] < 1.0 else "none")
                print(f"| {family} | {p0:g} | {r['alpha0']:g} | {fine_ratio(r['mesostructure']):.4g} | "
                      + ("- | - | - | - |" if math.isnan(fp) else
                         f"{fp / p0:.3f} | {r['p_at_first_peak'] / p0:.3f} | {100 * r['eps1_at_first_peak']:.2f} | "
                         f"{fp / r['p_at_first_peak']:.3f} |"))
            if len(peaks) >= 2:
                p, q = np.array(peaks).T
                slope = float(p @ q / (p @ p))
                slopes[(family, p0)] = (slope, float(np.abs(q - slope * p).max()), len(peaks))
                xs = np.linspace(0.0, 1.2, 2)
                ax.plot(xs, slope * xs, color="k", ls=styles[family], lw=1.3,
                        label=f"{family}: $q = {slope:.3f}\\,p$")
    for p0, ax in axes.items():
        ax.set(xlabel=LABELS["p/p0"], ylabel=LABELS["q/p0"], xlim=(0.0, 2.0), ylim=(0.0, 1.6),
               title=f"$p_0 = {number(p0)}$ N/m: stress paths, first $q$ peaks (filled: $p < p_0$), instability lines")
        ax.title.set_fontsize(9)
        ax.grid(True, **GRID)
        ax.legend(fontsize=6, ncols=2)  # each panel its own instability lines
    fig.suptitle("line styles / markers: " + ", ".join(f"{f} {styles[f]} {markers[f]}" for f in families), fontsize=9)
    figures.save_figure(apply_style(fig), figures / "gap_instability.png")
    print("\nLine q = eta_IL p through the origin, least squares over the first peaks reached with p < p0 "
          "(contractive cells; open markers in the figure are the others):\n")
    print("| cell | p0 [N/m] | peaks | slope eta_IL | max abs(q - eta_IL p) / p0 |")
    print("|---|---|---|---|---|")
    for (family, p0), (slope, scatter, n) in slopes.items():
        print(f"| {family} | {p0:g} | {n} | {slope:.3f} | {scatter:.3f} |")


def erosion(runs: Path, figures: Path) -> None:
    print("\n| alpha0 | p0 [N/m] | r_f / r | erode at [%] | p/p0 just before | just after | p/p0 at 15 % | plain at 15 % | "
          "fines kept at 15 % |")
    print("|---|---|---|---|---|---|---|---|---|")
    fig = Figure(figsize=(12.0, 8.5), layout="constrained")
    grid = fig.subplots(2, 2)
    for col, (alpha0, base) in enumerate(((50.0, "gap_a50"), (55.0, "gap_a55"))):
        reference = sweep.read_summary(runs / base / sweep.SUMMARY_FILE)
        for row_index, p0 in enumerate((2e5, 5.85e6)):
            ax = grid[row_index, col]
            plain = next(r for r in reference if r["mesostructure"] == "hcell" and r["p0"] == p0)
            c = curve(runs / base, plain)
            ax.plot(100 * c.eps1, c.p / p0, color="k", label="plain")
            fines_text = None
            for eps, ls in ((5, "--"), (10, ":")):
                folder = runs / f"gap_erode_a{alpha0:g}_{eps}"
                if not folder.is_dir():
                    continue
                row = next(r for r in sweep.read_summary(folder / sweep.SUMMARY_FILE) if r["p0"] == p0)
                fines_text = row["mesostructure"]
                record = io.read_run(folder / sweep.CASES_DIR / row["case"] / io.RUN_FILE).record
                before = record.p[record.stage == "shear"][-1] / p0
                after = record.p[record.stage == "erode"][0] / p0
                kept = next(r for r in reference if r["mesostructure"] == fines_text and r["p0"] == p0)
                print(f"| {alpha0:g} | {p0:g} | {fine_ratio(fines_text):g} | {eps} | {before:.3f} | {after:.3f} | "
                      f"{row['p_at_15pct'] / p0:.3f} | {plain['p_at_15pct'] / p0:.3f} | {kept['p_at_15pct'] / p0:.3f} |")
                e = figures.shear_curve(record)
                ax.plot(100 * e.eps1, e.p / p0, ls=ls, color="tab:red", label=f"fines removed at {eps} %")
            if fines_text is not None:
                kept = next(r for r in reference if r["mesostructure"] == fines_text and r["p0"] == p0)
                k = curve(runs / base, kept)
                ax.plot(100 * k.eps1, k.p / p0, color="tab:blue", label=f"{fines_text} kept")
            ax.set(yscale="log", xlabel=LABELS["eps1"], ylabel=LABELS["p/p0"],
                   title=f"$\\alpha_0$ = {alpha0:g}°, $p_0 = {number(p0)}$ N/m")
            ax.grid(True, which="both", **GRID)
            ax.legend(fontsize=7)  # each column its own fines cell
    figures.save_figure(apply_style(fig), figures / "gap_erosion.png")


def ann_table(runs: Path, name: str = "sweep") -> None:
    """DEM vs ANN of every (mesostructure, alpha0, p0) of runs/gap_ann/<name> run by both backends."""
    folder = runs / "gap_ann" / name
    if not (folder / sweep.SUMMARY_FILE).is_file():
        print(f"(no {folder / sweep.SUMMARY_FILE}: DEM vs ANN table skipped)")
        return
    rows = sweep.read_summary(folder / sweep.SUMMARY_FILE)
    by_case = {(r["mesostructure"], r["alpha0"], r["p0"], r["backend"]): r for r in rows}
    print("| cell | alpha0 | p0 [N/m] | max abs(dp)/p0 | max abs(dq)/p0 | p/p0 at 15 % DEM | ANN | peak q/p0 DEM | ANN "
          "| unconverged DEM cell-increments | ANN cell-increments: tension-clipped / mechanism / Coulomb-capped "
          "/ all |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (meso, alpha0, p0, backend), dem in sorted(by_case.items()):
        ann = by_case.get((meso, alpha0, p0, "ann"))
        if backend != "dem" or ann is None:
            continue
        c_dem, c_ann = curve(folder, dem), curve(folder, ann)
        dp = np.abs(np.interp(c_dem.eps1, c_ann.eps1, c_ann.p) - c_dem.p).max() / p0
        dq = np.abs(np.interp(c_dem.eps1, c_ann.eps1, c_ann.q) - c_dem.q).max() / p0
        print(f"| {meso} | {alpha0:g} | {p0:g} | {dp:.4f} | {dq:.4f} | {dem['p_at_15pct'] / p0:.3f} | "
              f"{ann['p_at_15pct'] / p0:.3f} | {dem['peak_q'] / p0:.3f} | {ann['peak_q'] / p0:.3f} | "
              f"{dem['n_unconverged']:.0f} | {ann_counts(folder, ann)} |")


def ann_counts(folder: Path, row: dict) -> str:
    """Cell-increments of an ANN case where the backend's contact rules fired (``AnnCell`` diagnostics)."""
    record = io.read_run(folder / sweep.CASES_DIR / row["case"] / io.RUN_FILE).record
    counts = [int(np.nansum(record.diagnostics.get(name, np.zeros(1))))
              for name in ("n_tension_clipped", "n_mechanism", "n_coulomb_capped")]
    return " / ".join(str(c) for c in counts) + f" / {record.n_increments * record.theta_deg.size}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, default=Path("runs"))
    parser.add_argument("--figures", type=Path, default=Path("docs/figures"))
    args = parser.parse_args()
    fines_table(args.runs, args.figures)
    instability(args.runs, args.figures)
    erosion(args.runs, args.figures)
    ann_table(args.runs)


if __name__ == "__main__":
    main()
