"""The 2x2 biaxial-test figure, several backends overlaid.

Panels: q vs eps1; q vs p (stress path in the Cambridge plane); p vs eps1 (drained tests:
eps_v vs eps1); q/p vs eps1 (or W2 vs eps1). The half-difference t = q/2 can replace q. eps1 and eps_v are counted from the end of the
first (isotropic) stage, whose end point starts every curve. ``make_figure`` builds the
figure from ``{label: Record}``; ``save_figure`` writes it atomically as PNG, PDF or SVG
(by the file suffix).

Command line (``hmodel plot``, ``python -m homogenization.plotting``)::

    hmodel plot RUN.h5 [RUN.h5 ...] --out fig.png|fig.pdf|fig.svg [--deviator t] [--fourth-panel W2]

overlays finished runs; whether the third panel shows p or eps_v is read from the files
(``drained`` parameter, else: a stress-controlled component after the first step).

Sign convention: compression and contraction positive; stresses in N/m (2D).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from homogenization import invariants, io
from warp_hcell.cli import (
    Parser, UserError, atomic_write, check_output_path, command_prog, run_main, say, set_verbosity, verbosity_parser)
from homogenization.driver import Record

FOURTH_PANELS = ("q/p", "W2")
"""Choices of the fourth panel."""
LINE_STYLES = ("-", "--", ":", "-.")
"""Line style of the 1st, 2nd, ... run, so that coinciding backends remain distinguishable."""
DEVIATORS = ("q", "t")
"""Deviator measure drawn: q = sigma11 - sigma22 or t = q / 2."""
FORMATS = ("png", "pdf", "svg")
"""Figure file formats, chosen by the file suffix."""


@dataclass(frozen=True)
class ShearCurve:
    """Shear-stage curves of a record, starting at the end of its first stage.

    Attributes:
        eps1: axial strain eps11 counted from the end of stage 1 [-], shape (m + 1,).
        eps_v: volumetric strain eps11 + eps22 counted from the end of stage 1 [-], shape
            (m + 1,), contraction positive.
        p: mean stress [N/m], shape (m + 1,).
        q: deviator sigma11 - sigma22 [N/m], shape (m + 1,).
        w2: second-order work of each increment [N/m], shape (m,).
    """

    eps1: np.ndarray
    eps_v: np.ndarray
    p: np.ndarray
    q: np.ndarray
    w2: np.ndarray


def shear_curve(record: Record) -> ShearCurve:
    """Curves after the first stage of ``record`` (its whole history if it has one stage).

    The first point is the state at the end of stage 1 (the force-free initial state if the
    record has a single stage).
    """
    first = record.stage[0] if record.n_increments else ""
    n_first = int(np.argmax(record.stage != first)) if np.any(record.stage != first) else 0
    start = n_first - 1  # index of the last increment of stage 1, -1 for the initial state

    def tail(values: np.ndarray) -> np.ndarray:
        head = values[start] if start >= 0 else 0.0
        return np.concatenate([[head], values[n_first:]])

    e11, e22 = tail(record.eps11), tail(record.eps22)
    s11, s22, s12 = tail(record.sigma11), tail(record.sigma22), tail(record.sigma12)
    return ShearCurve(
        eps1=e11 - e11[0],
        eps_v=invariants.volumetric_strain(e11, e22) - (e11[0] + e22[0]),
        p=invariants.mean_stress(s11, s22),
        q=invariants.deviator(s11, s22),
        w2=invariants.second_order_work(s11, s22, s12, e11, e22),
    )


def make_figure(runs: Mapping[str, Record], *, drained: bool = False, fourth: str = "q/p", deviator: str = "q",
                title: str | None = None) -> Figure:
    """2x2 figure of the shear stage of every run in ``runs`` (label -> record), overlaid.

    Args:
        runs: curves to draw, keyed by legend label (e.g. backend name).
        drained: third panel shows eps_v vs eps1 instead of p vs eps1.
        fourth: "q/p" or "W2" for the fourth panel.
        deviator: "q" (sigma11 - sigma22) or "t" (half of it) on the deviator axes.
        title: figure title.
    """
    if fourth not in FOURTH_PANELS:
        raise ValueError(f"fourth panel {fourth!r} is not one of {FOURTH_PANELS}")
    if deviator not in DEVIATORS:
        raise ValueError(f"deviator {deviator!r} is not one of {DEVIATORS}")
    factor = 1.0 if deviator == "q" else 0.5
    if not runs:
        raise ValueError("nothing to plot: no runs given")
    fig = Figure(figsize=(11.0, 8.5), layout="constrained")
    (ax_q, ax_pq), (ax_3, ax_4) = fig.subplots(2, 2)
    eps1_label = r"$\varepsilon_1 = \varepsilon_{11}$ since the end of stage 1 [%]"
    q_label = r"$q = \sigma_{11} - \sigma_{22}$ [N/m]" if deviator == "q" else r"$t = (\sigma_{11} - \sigma_{22})/2$ [N/m]"
    p_label = r"$p = (\sigma_{11} + \sigma_{22})/2$ [N/m]"
    for i, (label, record) in enumerate(runs.items()):
        c = shear_curve(record)
        pct = 100.0 * c.eps1
        style = {"label": label, "linestyle": LINE_STYLES[i % len(LINE_STYLES)]}  # overlays stay visible
        ax_q.plot(pct, factor * c.q, **style)
        ax_pq.plot(c.p, factor * c.q, **style)
        if drained:
            ax_3.plot(pct, 100.0 * c.eps_v, **style)
        else:
            ax_3.plot(pct, c.p, **style)
        if fourth == "W2":
            ax_4.plot(0.5 * (pct[1:] + pct[:-1]), c.w2, **style)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                ax_4.plot(pct, np.where(c.p > 0.0, factor * c.q / c.p, np.nan), **style)
    ax_q.set(xlabel=eps1_label, ylabel=q_label, title="deviator")
    ax_pq.set(xlabel=p_label, ylabel=q_label, title="stress path (Cambridge plane)")
    if drained:
        ax_3.set(xlabel=eps1_label,
                 ylabel=r"$\varepsilon_v = \varepsilon_{11} + \varepsilon_{22}$ since stage 1 [%]",
                 title="volumetric strain (contraction > 0)")
    else:
        ax_3.set(xlabel=eps1_label, ylabel=p_label, title="mean stress")
    if fourth == "W2":
        ax_4.set(xlabel=eps1_label, ylabel=r"$W_2 = d\sigma : d\varepsilon$ per increment [N/m]",
                 title="second-order work")
        ax_4.axhline(0.0, color="0.6", lw=0.8)
    else:
        ax_4.set(xlabel=eps1_label, ylabel=f"${deviator}/p$ [-]", title="stress ratio")
    for ax in (ax_q, ax_pq, ax_3, ax_4):
        ax.grid(True, alpha=0.3)
        ax.legend()
    if title:
        fig.suptitle(title + " (compression positive)")
    return fig


def figure_format(path: Path) -> str:
    """File format of figure ``path`` from its suffix; UserError (one line) if not in ``FORMATS``."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        raise UserError(f"{path}: figure suffix must be one of {', '.join('.' + f for f in FORMATS)}")
    return suffix


def save_figure(fig: Figure, path: Path, *, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` atomically, as PNG, PDF or SVG by the suffix; returns ``path``."""
    path = Path(path)
    fmt = figure_format(path)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi)
    return path


def is_drained(parameters: Mapping, programme: Sequence) -> bool:
    """Whether a stored run is drained: its ``drained`` parameter, else a stress-controlled
    component in any step after the first (``programme`` as ``loading.Programme``)."""
    if "drained" in parameters and parameters["drained"] is not None:
        return bool(parameters["drained"])
    return any(any(step.stress_mask) for step in programme[1:])


def run_labels(paths: Sequence[Path], backends: Sequence[str]) -> list[str]:
    """Legend labels: the backend, followed by the run's folder where a backend appears twice."""
    if len(set(backends)) == len(backends):
        return list(backends)
    labels = [f"{backend} ({Path(path).parent.name or Path(path).stem})" for path, backend in zip(paths, backends)]
    if len(set(labels)) < len(labels):
        labels = [f"{backend} ({path})" for path, backend in zip(paths, backends)]
    return labels


def build_parser() -> argparse.ArgumentParser:
    """Parser of the replot command."""
    parser = Parser(
        prog=command_prog("homogenization.plotting"), parents=[verbosity_parser()],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Overlay finished runs (run.h5 files of hmodel biaxial) in the 2x2 biaxial figure.")
    parser.add_argument("runs", type=Path, nargs="+", metavar="RUN.h5", help="run files to overlay")
    parser.add_argument("--out", type=Path, required=True, help="figure file: .png, .pdf or .svg")
    parser.add_argument("--deviator", choices=DEVIATORS, default=DEVIATORS[0], help="q = s11 - s22 or t = q/2")
    parser.add_argument("--fourth-panel", choices=FOURTH_PANELS, default=FOURTH_PANELS[0],
                        help="fourth panel: stress ratio or second-order work W2")
    parser.add_argument("--title", default=None, help="figure title (default: the runs' alpha0 and p0)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing figure")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    figure_format(args.out)
    if args.out.is_dir():
        raise UserError(f"--out {args.out} is a folder; give a file name")
    check_output_path(args.out, overwrite=args.overwrite)
    stored = [io.read_run(path) for path in args.runs]
    drained = {is_drained(run.attrs["parameters"], run.record.programme) for run in stored}
    if len(drained) > 1:
        raise UserError("the runs mix drained and constant-volume tests; plot each kind separately")
    labels = run_labels(args.runs, [run.record.backend for run in stored])
    title = args.title
    if title is None:
        cases = dict.fromkeys(f"alpha0 = {run.record.alpha0_deg:g} deg, p0 = {run.attrs['parameters'].get('p0', float('nan')):g} N/m"
                              for run in stored)
        title = "; ".join(cases)
    fig = make_figure(dict(zip(labels, (run.record for run in stored))), drained=drained.pop(),
                      fourth=args.fourth_panel, deviator=args.deviator, title=title)
    try:
        save_figure(fig, args.out)
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    say(f"figure -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
