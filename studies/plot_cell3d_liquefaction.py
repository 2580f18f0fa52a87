"""Figure of undrained triaxial tests of 3D cells side by side: p/p0 (log scale) and q/p0 against the
axial strain of the shear stage, from the ``curve.csv`` files of ``hmodel triaxial`` runs.

Usage: python studies/plot_cell3d_liquefaction.py --p0 2e5 --out FIG.png LABEL=RUN_DIR/curve.csv ...
Stresses in the files in Pa, compression positive; the shear stage is the rows of stage ``shear``,
its axial strain counted from the end of the isotropic stage.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from homogenization.output.figure_style import GRID, PNG_DPI, apply_style, figure_legend


def shear_curve(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(axial strain of the shear stage [-], p [Pa], q [Pa]) of a ``curve.csv``."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    start = float([r for r in rows if r["stage"] == "iso"][-1]["eps11"])
    shear = [r for r in rows if r["stage"] == "shear"]
    return (np.array([float(r["eps11"]) for r in shear]) - start, np.array([float(r["p"]) for r in shear]),
            np.array([float(r["q"]) for r in shear]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--p0", type=float, required=True, help="isotropic pressure of the runs [Pa]")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("runs", nargs="+", help="LABEL=path/to/curve.csv")
    args = parser.parse_args()
    fig = Figure(figsize=(11, 4.6), layout="constrained")
    ax_p, ax_q = fig.subplots(1, 2)
    handles = []
    for item in args.runs:
        label, _, path = item.rpartition("=")  # the label may hold "=", the path does not
        eps, p, q = shear_curve(Path(path))
        (line,) = ax_p.semilogy(100 * eps, p / args.p0, label=label)
        ax_q.plot(100 * eps, q / args.p0, color=line.get_color())
        handles.append(line)
    ax_p.axhline(0.3, color="0.4", lw=0.8, ls=":")
    ax_p.set(xlabel=r"$\varepsilon_a$ since the end of the isotropic stage [%]", ylabel=r"$p / p_0$ [-]",
             title="mean stress")
    ax_q.set(xlabel=r"$\varepsilon_a$ since the end of the isotropic stage [%]", ylabel=r"$q / p_0$ [-]",
             title=r"deviator $q = \sqrt{3 J_2}$")
    for ax in (ax_p, ax_q):
        ax.grid(**GRID)
    apply_style(fig)
    ticks = [0.1, 0.3, 1.0, 3.0, 10.0, 30.0]
    ax_p.set_yticks(ticks, [f"{t:g}" for t in ticks])
    ax_p.set_ylim(0.1, 30.0)
    fig.suptitle(f"undrained triaxial compression, $p_0$ = {args.p0:g} Pa (compression positive)")
    figure_legend(fig, handles)
    fig.savefig(args.out, dpi=PNG_DPI, bbox_inches="tight")
    print(f"figure -> {args.out}")


if __name__ == "__main__":
    main()
