"""The 2x2 biaxial-test figure, several runs overlaid, and the triaxial figure.

Panels: q vs eps1; q vs p (Cambridge plane); p vs eps1 (drained tests: eps_v vs eps1); q/p vs
eps1 (or W2 vs eps1). t = q/2 can replace q, and stresses can be drawn over each run's p0. eps1
and eps_v are counted from the end of the first (isotropic) stage. ``make_figure`` builds the
figure from ``{label: Record}``; ``overlay_figure`` from stored runs, titled and labelled from
their metadata (``run_labels``); ``save_figure`` writes PNG, PDF or SVG atomically (by suffix).
Tick format and axis labels: ``figure_style``. The command ``hmodel plot`` is
``homogenization.cli.plot``.

Critical-state line (``--csl``): q = M p, M by least squares through the origin over the last
10 % of the shear-stage points with p > 0.05 p0 (``critical_state``), drawn only where p, q and
eps_v are steady over that span (abs(dp/deps1)/p <= 0.1, abs(dq/deps1)/p <= 0.1,
abs(deps_v/deps1) <= 0.01), q/p is stationary (range <= 0.1) and the run did not end near the
origin; any other run gets a one-line warning naming the rate that failed.

Triaxial (3D) runs: ``triaxial_figure`` draws (p, q), (eps_a, q) and (eps_a, eps_v), eps_a =
eps11, eps_v = 1 - V/V1 from the end of the isotropic stage, p = tr(sigma) / 3, q = sqrt(3 J2).

Volumetric-strain panels: a run whose eps_v is round-off only (abs(eps_v) <= ``ROUND_OFF`` max
abs(eps1)) is drawn at exactly 0, with the note "eps_v held at 0".

Sign convention: compression and contraction positive; stresses in N/m (2D), Pa (3D).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from homogenization.material import invariants
from homogenization.output import run_labels
from homogenization.element_test.driver import Record
from homogenization.output.figure_style import apply_style, figure_legend, GRID, LABELS, number, PNG_DPI
from warp_hcell.core.errors import UserError
from warp_hcell.core.files import atomic_write

FOURTH_PANELS = ("q/p", "W2")
"""Choices of the fourth panel."""
LINE_STYLES = ("-", "--", ":", "-.")
"""Line style of the 1st, 2nd, ... run, so that coinciding backends remain distinguishable."""
DEVIATORS = ("q", "t")
"""Deviator measure drawn: q = sigma11 - sigma22 or t = q / 2."""
FORMATS = ("png", "pdf", "svg")
"""Figure file formats, chosen by the file suffix."""
ROUND_OFF = 1e-9
"""A volumetric-strain curve whose largest abs(eps_v) is at most ROUND_OFF times its largest abs(eps1) holds
only round-off (an isochoric test): it is drawn at exactly 0 and its panel says so (``held_at_zero``) [-]."""
HELD_AT_ZERO_LIMITS = (-1.0, 1.0)
"""y limits [%] of a volumetric-strain panel whose every curve is held at 0 (no axis scaled to round-off)."""
CSL_TAIL = 0.1
"""Fraction of the shear-stage points, at its end, that the critical-state line is fitted to."""
CSL_MIN_POINTS = 3
"""Fewest points the critical-state fit looks at (short runs)."""
CSL_MIN_P = 0.05
"""Points with p <= CSL_MIN_P p0 are left out of the critical-state fit [-]."""
CSL_MAX_SPREAD = 0.1
"""Largest range max(q/p) - min(q/p) over the fitted points for the end to count as a critical state [-]."""
CSL_MIN_RATIO = 0.02
"""Smallest abs(q/p) over the fitted points for a critical state [-]: an end nearly without deviator (e.g. a run
unloaded to q = 0, where p, q and the volume are steady too) is no critical state of shearing."""
CSL_MAX_P_RATE = 0.1
"""Largest abs(dp/deps1) / p over the fitted points for a critical state [-]: p moves by at most 0.1 % of
itself per 1 % of axial strain."""
CSL_MAX_Q_RATE = 0.1
"""Largest abs(dq/deps1) / p over the fitted points for a critical state [-]."""
CSL_MAX_V_RATE = 0.01
"""Largest abs(deps_v/deps1) over the fitted points for a critical state [-] (volume steady)."""
CSL_LINE_STYLE = (0, (6, 2, 1, 2))
"""Dash pattern of critical-state lines (apart from the run line styles)."""
CSL_LABEL = "critical-state line $q = M p$"
"""Legend text of the critical-state lines."""
CSL_RULE = (f"q = M p, M by least squares through the origin over the last {100 * CSL_TAIL:g} % of the shear-stage "
            f"points with p > {CSL_MIN_P:g} p0, drawn only where the run reached a critical state there: "
            f"least-squares rates against eps1 of abs(dp/deps1)/p <= {CSL_MAX_P_RATE:g}, "
            f"abs(dq/deps1)/p <= {CSL_MAX_Q_RATE:g} and abs(deps_v/deps1) <= {CSL_MAX_V_RATE:g}, q/p ranging over "
            f"at most {CSL_MAX_SPREAD:g} and abs(q/p) at least {CSL_MIN_RATIO:g} (sheared), fewer than half of "
            f"those points near the origin (static liquefaction); "
            f"any other run gets no line and a one-line warning")
"""The critical-state rule, as in --help and docs/programmes.md."""


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


TRIAXIAL_LABELS = {
    "eps_a": r"$\varepsilon_a = \varepsilon_{11}$ since the end of stage 1 [%]",
    "eps_v": r"$\varepsilon_v = 1 - V/V_1$ since the end of stage 1 [%]",
    "p": r"$p = \mathrm{tr}\,\sigma / 3$ [Pa]",
    "q": r"$q = \sqrt{3 J_2}$ [Pa]",
}
"""Axis labels of the triaxial figure (mathtext); strains in %, stresses in Pa."""


@dataclass(frozen=True)
class TriaxialCurve:
    """Curves of a 3D record after its first stage, starting at the end of it.

    Attributes:
        eps_a: axial strain eps11 since the end of stage 1 [-], shape (m + 1,).
        eps_v: 1 - V/V1 since the end of stage 1 (volume V1) [-], shape (m + 1,), contraction positive.
        p: tr(sigma) / 3 [Pa], shape (m + 1,).
        q: sqrt(3 J2) [Pa], shape (m + 1,).
    """

    eps_a: np.ndarray
    eps_v: np.ndarray
    p: np.ndarray
    q: np.ndarray


def triaxial_curve(record: Record) -> TriaxialCurve:
    """``TriaxialCurve`` of a 3D ``record`` (ValueError for a planar one); its stored p and q."""
    if record.dim != 3:
        raise ValueError("a triaxial figure needs a 3D run (eps33 and sigma33)")
    first = record.stage[0] if record.n_increments else ""
    n_first = int(np.argmax(record.stage != first)) if np.any(record.stage != first) else 0
    start = n_first - 1

    def tail(values: np.ndarray) -> np.ndarray:
        head = values[start] if start >= 0 else 0.0
        return np.concatenate([[head], values[n_first:]])

    e11 = tail(record.eps11)
    J = np.concatenate([[record.J[start] if start >= 0 else 1.0], record.J[n_first:]])
    return TriaxialCurve(eps_a=e11 - e11[0], eps_v=1.0 - J / J[0], p=tail(record.p), q=tail(record.q))


def held_at_zero(eps1: np.ndarray, eps_v: np.ndarray) -> bool:
    """Whether ``eps_v`` holds only round-off next to ``eps1`` (same unit): max abs(eps_v) <= ``ROUND_OFF`` max abs(eps1)."""
    return float(np.max(np.abs(eps_v), initial=0.0)) <= ROUND_OFF * float(np.max(np.abs(eps1), initial=0.0))


def volume_drawn(eps1: np.ndarray, eps_v: np.ndarray) -> np.ndarray:
    """``eps_v`` as drawn: exact zeros where it is round-off only (``held_at_zero``), else itself."""
    return np.zeros_like(eps_v) if held_at_zero(eps1, eps_v) else eps_v


def mark_held_at_zero(ax) -> None:
    """Fixed limits ``HELD_AT_ZERO_LIMITS`` and a note on a volumetric-strain panel whose every curve is held at 0."""
    ax.set_ylim(*HELD_AT_ZERO_LIMITS)
    ax.text(0.5, 0.6, f"$\\varepsilon_v$ held at 0\n(isochoric: round-off only, below ${number(ROUND_OFF)}$ "
                      f"of the axial strain)", transform=ax.transAxes, ha="center", va="bottom", fontsize="small",
            color="0.3")


def triaxial_figure(runs: Mapping[str, Record], *, title: str | None = None) -> Figure:
    """Three panels of the shear stage of every 3D run in ``runs`` (label -> record), overlaid:
    (p, q), (eps_a, q), (eps_a, eps_v) (module docstring); one legend below the panels."""
    if not runs:
        raise ValueError("nothing to plot: no runs given")
    curves, held = [], []
    for i, (label, record) in enumerate(runs.items()):
        c = triaxial_curve(record)
        held.append(held_at_zero(c.eps_a, c.eps_v))
        curves.append((label, {"linestyle": LINE_STYLES[i % len(LINE_STYLES)]},
                       ((c.p, c.q), (100.0 * c.eps_a, c.q), (100.0 * c.eps_a, 100.0 * volume_drawn(c.eps_a, c.eps_v)))))
    panels = ((TRIAXIAL_LABELS["p"], TRIAXIAL_LABELS["q"], "stress path"),
              (TRIAXIAL_LABELS["eps_a"], TRIAXIAL_LABELS["q"], "deviator"),
              (TRIAXIAL_LABELS["eps_a"], TRIAXIAL_LABELS["eps_v"], "volumetric strain (contraction > 0)"))
    fig = panel_figure(curves, panels, figsize=(14.0, 4.8), title=title + " (compression positive)" if title else None)
    if all(held):
        mark_held_at_zero(fig.axes[2])
    return fig


def panel_figure(curves: Sequence[tuple[str | None, Mapping[str, Any], Sequence[tuple[np.ndarray, np.ndarray]]]],
                 panels: Sequence[tuple[str, str, str]], *, figsize: tuple[float, float],
                 title: str | None = None) -> Figure:
    """Panels side by side, every curve drawn in each; one legend below them.

    Args:
        curves: (label, line style, one (x, y) per panel) per curve; a curve keeps the colour
            of its first panel in the others; an empty or None label leaves it out of the legend.
        panels: (x label, y label, title) per panel.
        figsize: the figure's size [in].
        title: the figure's title (None: none).
    """
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(1, len(panels))
    handles = []
    for label, line_style, xy in curves:
        style = dict(line_style)
        (line,) = axes[0].plot(*xy[0], label=label or "_nolegend_", **style)
        style["color"] = line.get_color()
        for ax, (x, y) in zip(axes[1:], xy[1:]):
            ax.plot(x, y, **style)
        if label:
            handles.append(line)
    for ax, (xlabel, ylabel, panel_title) in zip(axes, panels):
        ax.set(xlabel=xlabel, ylabel=ylabel, title=panel_title)
        ax.grid(True, **GRID)
    if handles:
        figure_legend(fig, handles)
    if title:
        fig.suptitle(title)
    return apply_style(fig)


def _stress_label(name: str, normalised: bool) -> str:
    return LABELS[f"{name}/p0" if normalised else name]


def make_figure(runs: Mapping[str, Record], *, drained: bool = False, fourth: str = "q/p", deviator: str = "q",
                title: str | None = None, normalise: Mapping[str, float] | None = None,
                csl: Mapping[str, float] | None = None) -> Figure:
    """2x2 figure of the shear stage of every run in ``runs`` (label -> record), overlaid.

    One legend below the panels lists the runs with a non-empty label (with their slope M) and the
    critical-state line style; none if there is nothing to list.

    Args:
        runs: curves to draw, keyed by legend label ("" for no legend entry).
        drained: third panel shows eps_v vs eps1 instead of p vs eps1.
        fourth: "q/p" or "W2" for the fourth panel.
        deviator: "q" (sigma11 - sigma22) or "t" (half of it) on the deviator axes.
        title: figure title.
        normalise: p0 [N/m] of every label: stresses (and W2) are drawn divided by it.
        csl: slope M of the critical-state line q = M p by label (none: no line); in the t axes
            the line is t = M p / 2."""
    if fourth not in FOURTH_PANELS:
        raise ValueError(f"fourth panel {fourth!r} is not one of {FOURTH_PANELS}")
    if deviator not in DEVIATORS:
        raise ValueError(f"deviator {deviator!r} is not one of {DEVIATORS}")
    factor = 1.0 if deviator == "q" else 0.5
    if not runs:
        raise ValueError("nothing to plot: no runs given")
    if normalise is not None:
        missing = [label for label in runs if not normalise.get(label)]
        if missing:
            raise ValueError(f"no p0 to normalise the run {missing[0]!r} by")
    normalised = normalise is not None
    csl = csl or {}
    fig = Figure(figsize=(11.0, 8.5), layout="constrained")
    (ax_q, ax_pq), (ax_3, ax_4) = fig.subplots(2, 2)
    handles, held = [], []
    for i, (label, record) in enumerate(runs.items()):
        c = shear_curve(record)
        scale = 1.0 / normalise[label] if normalised else 1.0
        p, q = scale * c.p, scale * factor * c.q
        pct = 100.0 * c.eps1
        style = {"label": label or "_nolegend_", "linestyle": LINE_STYLES[i % len(LINE_STYLES)]}
        (line,) = ax_q.plot(pct, q, **style)
        style["color"] = line.get_color()
        ax_pq.plot(p, q, **style)
        if drained:
            held.append(held_at_zero(c.eps1, c.eps_v))
            ax_3.plot(pct, 100.0 * volume_drawn(c.eps1, c.eps_v), **style)
        else:
            ax_3.plot(pct, p, **style)
        if fourth == "W2":
            ax_4.plot(0.5 * (pct[1:] + pct[:-1]), scale * c.w2, **style)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                ax_4.plot(pct, np.where(c.p > 0.0, factor * c.q / c.p, np.nan), **style)
        if label in csl:
            slope = csl[label]
            p_end = float(np.nanmax(p)) if p.size else 0.0
            (csl_line,) = ax_pq.plot([0.0, p_end], [0.0, factor * slope * p_end], color=style["color"], lw=1.0,
                                     linestyle=CSL_LINE_STYLE)
            if label:
                line.set_label(f"{label}; $M$ = {slope:.3f}")
            else:
                csl_line.set_label(f"{CSL_LABEL}, $M$ = {slope:.3f}")
                handles.append(csl_line)
        if label:
            handles.append(line)
    deviator_label = _stress_label(deviator, normalised)
    p_label = _stress_label("p", normalised)
    ax_q.set(xlabel=LABELS["eps1"], ylabel=deviator_label, title="deviator")
    ax_pq.set(xlabel=p_label, ylabel=deviator_label, title="stress path (Cambridge plane)")
    if drained:
        ax_3.set(xlabel=LABELS["eps1"], ylabel=LABELS["eps_v"], title="volumetric strain (contraction > 0)")
        if all(held):
            mark_held_at_zero(ax_3)
    else:
        ax_3.set(xlabel=LABELS["eps1"], ylabel=p_label, title="mean stress")
    if fourth == "W2":
        ax_4.set(xlabel=LABELS["eps1"], ylabel=_stress_label("W2", normalised), title="second-order work")
        ax_4.axhline(0.0, color="0.6", lw=0.8)
    else:
        ax_4.set(xlabel=LABELS["eps1"], ylabel=LABELS[f"{deviator}/p"], title="stress ratio")
    for ax in (ax_q, ax_pq, ax_3, ax_4):
        ax.grid(True, **GRID)
    if csl and any(runs):
        handles.append(Line2D([], [], color="k", lw=1.0, linestyle=CSL_LINE_STYLE,
                              label="critical-state lines $q = M p$"))
    if handles:
        figure_legend(fig, handles)
    if title:
        fig.suptitle(title + " (compression positive)")
    return apply_style(fig)


@dataclass(frozen=True)
class Run:
    """A finished run to draw: its record and the ``parameters`` it stores (run.h5 attribute)."""

    record: Record
    parameters: Mapping[str, Any]


def reference_pressure(run: Run) -> float | None:
    """p0 of ``run`` [N/m]: its ``p0`` parameter, else the first ``stop_at_p`` of its programme, else None."""
    p0 = run.parameters.get("p0")
    if p0:
        return float(p0)
    return next((float(step.stop_at_p) for step in run.record.programme if step.stop_at_p), None)


def run_drained(run: Run) -> bool:
    """Whether ``run`` is a drained test (``is_drained`` of its parameters and programme)."""
    return is_drained(run.parameters, run.record.programme)


TRIAXIAL_NAMES = {"undrained": "undrained triaxial compression", "drained": "drained triaxial compression",
                  "extension": "drained triaxial extension", "constant_p": "triaxial compression at constant p",
                  "true": "true triaxial compression", "cyclic": "cyclic undrained triaxial test"}
"""What a 3D run is, by the ``test`` parameter that ``hmodel triaxial`` stores (``programme.TRIAXIAL_TESTS``)."""
TEST_NAMES = {2: lambda run: "drained biaxial test" if run_drained(run) else "constant-volume biaxial test",
              3: lambda run: TRIAXIAL_NAMES.get(str(run.parameters.get("test")), "triaxial test")}
"""What a run of cells of each dimension is, without a programme file: the biaxial test of a planar
run (drained or constant-volume), the triaxial test of a spatial one (``TRIAXIAL_NAMES``)."""


def programme_name(run: Run) -> str:
    """What the run is: "programme <file stem>", else the test of its dimension (``TEST_NAMES``)."""
    programme_file = run.parameters.get("programme_file")
    if programme_file:
        return f"programme {Path(programme_file).stem}"
    return TEST_NAMES[run.record.dim](run)


def describe_run(run: Run) -> dict[str, str]:
    """``run_labels.describe`` of a run, with the backend, alpha0 and N of its record as fall-backs."""
    record = run.record
    return run_labels.describe(run.parameters, test=programme_name(run), backend=record.backend,
                               alpha0_deg=record.parameters.get("alpha0_deg"), n_orientations=record.theta_deg.size,
                               dim=record.dim)


class NoCriticalState(ValueError):
    """A run whose end gives no critical-state line (the message, one line, says why)."""


@dataclass(frozen=True)
class CriticalState:
    """The critical state a run reached, and the measured rates that qualify it (``critical_state``).

    Attributes:
        slope: M of q = M p [-].
        eps1_span: first and last eps1 of the fitted points [-].
        p_rate: abs(dp/deps1) / p over them (least-squares slope over the mean p) [-].
        q_rate: abs(dq/deps1) / p over them [-].
        v_rate: abs(deps_v/deps1) over them [-].
    """

    slope: float
    eps1_span: tuple[float, float]
    p_rate: float
    q_rate: float
    v_rate: float

    def describe(self) -> str:
        """One line: M, the span and the rates against their limits."""
        lo, hi = self.eps1_span
        return (f"M = {self.slope:.3f} at a critical state over eps1 = {100 * lo:.3g}-{100 * hi:.3g} %: "
                f"|dp/deps1|/p = {self.p_rate:.2g}, |dq/deps1|/p = {self.q_rate:.2g}, "
                f"|deps_v/deps1| = {self.v_rate:.2g} (limits {CSL_MAX_P_RATE:g}, {CSL_MAX_Q_RATE:g}, "
                f"{CSL_MAX_V_RATE:g})")


def _rate(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope dy/dx of the points (x, y)."""
    dx = x - x.mean()
    return float(dx @ (y - y.mean()) / (dx @ dx))


def critical_state(curve: ShearCurve, p0: float) -> CriticalState:
    """The critical state at the end of a shear curve, with M of its line q = M p.

    Rule (``CSL_RULE``): the last ``CSL_TAIL`` of the shear-stage points (at least
    ``CSL_MIN_POINTS``) that have p > ``CSL_MIN_P`` p0; there p, q and eps_v must be steady
    (least-squares rates against eps1 within ``CSL_MAX_P_RATE``, ``CSL_MAX_Q_RATE`` and
    ``CSL_MAX_V_RATE``); M = sum(p q) / sum(p^2) by least squares through the origin.

    Raises:
        NoCriticalState: fewer than half of those points have p > CSL_MIN_P p0 (a run that
            ends near the origin: static liquefaction), q/p ranges over more than
            ``CSL_MAX_SPREAD`` among them (reversed or cyclic loading), abs(q/p) falls below ``CSL_MIN_RATIO``
            (an unsheared end, e.g. unloaded to q = 0), a rate exceeds its
            limit (p, q or the volume still changing), or the curve has no shear stage.
    """
    p, q, e1, ev = curve.p[1:], curve.q[1:], curve.eps1[1:], curve.eps_v[1:]
    if p.size == 0:
        raise NoCriticalState("no shear stage")
    n_tail = min(p.size, max(CSL_MIN_POINTS, math.ceil(CSL_TAIL * p.size)))
    p, q, e1, ev = p[-n_tail:], q[-n_tail:], e1[-n_tail:], ev[-n_tail:]
    keep = p > CSL_MIN_P * p0
    if 2 * int(keep.sum()) < n_tail:
        raise NoCriticalState(f"it ends at p = {curve.p[-1] / p0:.3g} p0 (liquefied): fewer than half of its last "
                              f"{100 * CSL_TAIL:g} % of points have p > {CSL_MIN_P:g} p0")
    p, q, e1, ev = p[keep], q[keep], e1[keep], ev[keep]
    ratio = q / p
    if ratio.max() - ratio.min() > CSL_MAX_SPREAD:
        raise NoCriticalState(f"q/p is not stationary over its last {100 * CSL_TAIL:g} % of points (from "
                              f"{ratio[0]:.3g} to {ratio[-1]:.3g}, range {ratio.max() - ratio.min():.3g} > "
                              f"{CSL_MAX_SPREAD:g}: reversed or cyclic loading)")
    if np.abs(ratio).min() < CSL_MIN_RATIO:
        raise NoCriticalState(f"its end is not sheared: abs(q/p) falls to {np.abs(ratio).min():.2g} < {CSL_MIN_RATIO:g} "
                              f"over its last {100 * CSL_TAIL:g} % of points")
    if p.size < 2 or e1.max() == e1.min():
        raise NoCriticalState("its last points span no axial strain: no rates to check")
    p_mean = float(p.mean())
    dp, dq, dv = _rate(e1, p) / p_mean, _rate(e1, q) / p_mean, _rate(e1, ev)
    state = CriticalState(slope=float(p @ q / (p @ p)), eps1_span=(float(e1.min()), float(e1.max())),
                          p_rate=abs(dp), q_rate=abs(dq), v_rate=abs(dv))
    failed = [f"{name} = {value:.2g} > {limit:g}" for name, value, limit in
              (("|dp/deps1|/p", state.p_rate, CSL_MAX_P_RATE), ("|dq/deps1|/p", state.q_rate, CSL_MAX_Q_RATE),
               ("|deps_v/deps1|", state.v_rate, CSL_MAX_V_RATE)) if value > limit]
    if failed:
        trends = [f"{what} still {'rising' if rate > 0 else 'falling'}" for what, rate, limit in
                  (("p", dp, CSL_MAX_P_RATE), ("q", dq, CSL_MAX_Q_RATE)) if abs(rate) > limit]
        if state.v_rate > CSL_MAX_V_RATE:
            trends.append(f"volume still {'contracting' if dv > 0 else 'dilating'}")
        lo, hi = state.eps1_span
        raise NoCriticalState(f"no critical state reached over eps1 = {100 * lo:.3g}-{100 * hi:.3g} % "
                              f"({', '.join(trends)}: {', '.join(failed)}); q/p there is {ratio[-1]:.3g}")
    return state


def critical_state_slope(curve: ShearCurve, p0: float) -> float:
    """M of ``critical_state(curve, p0)`` (NoCriticalState where the run reached none)."""
    return critical_state(curve, p0).slope


def critical_state_lines(runs: Sequence[Run], names: Sequence[str], warn: Callable[[str], None],
                         report: Callable[[str], None] | None = None) -> list[float | None]:
    """M of every run (None where ``critical_state`` refuses, with one ``warn`` line naming it);
    ``report`` (if given) gets one line per run with a line: M and the rates that qualify it."""
    slopes: list[float | None] = []
    for run, name in zip(runs, names):
        curve = shear_curve(run.record)
        p0 = reference_pressure(run) or float(curve.p[0]) or 1.0  # no p0: the mean stress the shear starts at
        try:
            state = critical_state(curve, p0)
        except NoCriticalState as exc:
            warn(f"{name}: no critical-state line: {exc}")
            slopes.append(None)
            continue
        if report is not None:
            report(f"{name}: {state.describe()}")
        slopes.append(state.slope)
    return slopes


def triaxial_runs(runs: Sequence[Run]) -> bool:
    """Whether ``runs`` are 3D runs, which ``overlay_figure`` draws as ``triaxial_figure`` (without the planar
    figure's options)."""
    return {run.record.dim for run in runs} == {3}


def overlay_figure(runs: Sequence[Run], *, fourth: str = "q/p", deviator: str = "q", normalise: bool = False,
                   csl: Sequence[float | None] | None = None, title: str | None = None) -> Figure:
    """The 2x2 figure of stored runs, labelled from their metadata (``run_labels.split_labels``);
    3D runs get the three panels of ``triaxial_figure`` instead (fourth, deviator, normalise and csl unused).

    The parts every run shares make the title (unless ``title`` is given), the parts that
    differ the legend labels; whether the third panel shows eps_v is read from the runs.

    Args:
        runs: runs to overlay, all drained or all not.
        fourth, deviator: as ``make_figure``.
        normalise: divide stresses by each run's p0 (``reference_pressure``).
        csl: slope M of each run's critical-state line (None: no line), e.g. from
            ``critical_state_lines``.
        title: replaces the title made from the shared parts.

    Raises:
        ValueError: no runs, drained and undrained runs mixed, or ``normalise`` with a run without p0.
    """
    if not runs:
        raise ValueError("nothing to plot: no runs given")
    dims = {run.record.dim for run in runs}
    if triaxial_runs(runs):
        common, labels = run_labels.split_labels([describe_run(run) for run in runs])
        return triaxial_figure(dict(zip(labels, (run.record for run in runs))), title=common if title is None else title)
    if len(dims) > 1:
        raise ValueError("the runs mix planar (biaxial) and 3D (triaxial) runs; plot each kind separately")
    drained = {run_drained(run) for run in runs}
    if len(drained) > 1:
        raise ValueError("the runs mix drained and constant-volume tests")
    common, labels = run_labels.split_labels([describe_run(run) for run in runs])
    p0 = dict(zip(labels, (reference_pressure(run) for run in runs)))
    slopes = {label: m for label, m in zip(labels, csl) if m is not None} if csl is not None else None
    return make_figure(dict(zip(labels, (run.record for run in runs))), drained=drained.pop(), fourth=fourth,
                       deviator=deviator, title=common if title is None else title,
                       normalise=p0 if normalise else None, csl=slopes)


def figure_format(path: Path) -> str:
    """File format of figure ``path`` from its suffix; UserError (one line) if not in ``FORMATS``."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        raise UserError(f"{path}: figure suffix must be one of {', '.join('.' + f for f in FORMATS)}")
    return suffix


def save_figure(fig: Figure, path: Path, *, dpi: int = PNG_DPI) -> Path:
    """Write ``fig`` to ``path`` atomically, as PNG, PDF or SVG by the suffix; returns ``path``."""
    path = Path(path)
    fmt = figure_format(path)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi)
    return path


def is_drained(parameters: Mapping, programme: Sequence) -> bool:
    """Whether a stored run is drained: its ``drained`` parameter, else a stress-controlled
    component in any step after the first (``programme``: its steps, a ``Programme``)."""
    if "drained" in parameters and parameters["drained"] is not None:
        return bool(parameters["drained"])
    return any(any(step.stress_mask) for step in programme[1:])
