"""The 2x2 biaxial-test figure of shared/spec/conventions.md, several backends overlaid.

Panels: q vs eps1; q vs p (stress path in the Cambridge plane); p vs eps1 (drained tests:
eps_v vs eps1); q/p vs eps1 (or W2 vs eps1). The half-difference t = q/2 can replace q. eps1 and eps_v are counted from the end of the
first (isotropic) stage, whose end point starts every curve. ``make_figure`` builds the
figure from ``{label: Record}``; ``save_figure`` writes it atomically.

Sign convention: compression and contraction positive; stresses in N/m (2D).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
from matplotlib.figure import Figure

from homogenization import invariants
from warp_hcell.cli import atomic_write
from homogenization.driver import Record

FOURTH_PANELS = ("q/p", "W2")
"""Choices of the fourth panel."""
LINE_STYLES = ("-", "--", ":", "-.")
"""Line style of the 1st, 2nd, ... run, so that coinciding backends remain distinguishable."""
DEVIATORS = ("q", "t")
"""Deviator measure drawn: q = sigma11 - sigma22 or t = q / 2."""


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


def save_figure(fig: Figure, path: Path, *, dpi: int = 120) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically; returns ``path``."""
    path = Path(path)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path
