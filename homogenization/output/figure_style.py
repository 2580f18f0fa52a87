"""The look shared by every figure the package writes: tick format, axis labels, numbers in text.

Figure modules (``plotting``, ``fe_output``, ``sweep``, the benchmark scripts) build their
figures with ``matplotlib.figure.Figure`` and call ``apply_style(fig)`` last: every linear
axis gets a ``TickFormatter`` (plain numbers up to 10^4, beyond that a common factor
written ``×10^n`` in mathtext at the end of the axis; no additive offset), log axes keep
matplotlib's ``LogFormatterSciNotation`` (also ``10^n`` in mathtext). A figure has one legend,
``figure_legend``, below its panels. Axis labels come from
``LABELS`` (mathtext symbols, units in brackets, strains in %); numbers written into titles
and legends go through ``number``. No global rcParams are changed.

Sign convention of the quantities named: compression and contraction positive; 2D stresses
in N/m, p = (sigma11 + sigma22)/2, q = sigma11 - sigma22.
"""

from __future__ import annotations

import math

from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.ticker import ScalarFormatter

PNG_DPI = 150
"""Resolution of PNG figures [dots per inch]."""
GRID = {"alpha": 0.3}
"""Grid line settings of every panel."""
LEGEND_COLUMNS = 3
"""Most columns of a figure legend."""
POWER_LIMITS = (-3, 4)
"""Tick labels use a common factor 10^n outside ``10^-3 <= abs(x) < 10^4`` (``ScalarFormatter.set_powerlimits``)."""

LABELS = {
    "eps1": r"$\varepsilon_1$ since the end of stage 1 [%]",
    "eps_v": r"$\varepsilon_v = \varepsilon_{11} + \varepsilon_{22}$ since the end of stage 1 [%]",
    "q": r"$q = \sigma_{11} - \sigma_{22}$ [N/m]",
    "t": r"$t = (\sigma_{11} - \sigma_{22})/2$ [N/m]",
    "p": r"$p = (\sigma_{11} + \sigma_{22})/2$ [N/m]",
    "q/p0": r"$q/p_0 = (\sigma_{11} - \sigma_{22})/p_0$ [-]",
    "t/p0": r"$t/p_0 = (\sigma_{11} - \sigma_{22})/(2 p_0)$ [-]",
    "p/p0": r"$p/p_0 = (\sigma_{11} + \sigma_{22})/(2 p_0)$ [-]",
    "q/p": r"$q/p$ [-]",
    "t/p": r"$t/p$ [-]",
    "W2": r"$W_2 = d\sigma : d\varepsilon$ per increment [N/m]",
    "W2/p0": r"$W_2/p_0$ per increment [-]",
    "eps_d": r"$\varepsilon_d = \sqrt{(\varepsilon_{xx} - \varepsilon_{yy})^2 + \gamma_{xy}^2}$ [-]",
    "x": r"$x$ [m]",
    "y": r"$y$ [m]",
}
"""Axis labels by quantity (mathtext); strains in %, stresses in N/m or over p0."""


class TickFormatter(ScalarFormatter):
    """Tick labels of every linear axis: mathtext, a ``×10^n`` factor outside ``POWER_LIMITS``, no offset."""

    def __init__(self) -> None:
        super().__init__(useOffset=False, useMathText=True)
        self.set_powerlimits(POWER_LIMITS)


def style_axes(ax: Axes) -> None:
    """Give the linear x and y axes of ``ax`` a ``TickFormatter`` (log axes keep theirs)."""
    for axis in (ax.xaxis, ax.yaxis):
        if axis.get_scale() == "linear":
            axis.set_major_formatter(TickFormatter())


def apply_style(fig: Figure) -> Figure:
    """``style_axes`` on every axes of ``fig`` (colour bars included); returns ``fig``."""
    for ax in fig.axes:
        style_axes(ax)
    return fig


def figure_legend(fig: Figure, handles: list[Artist], *, max_columns: int = LEGEND_COLUMNS) -> Legend:
    """The one legend of ``fig``, below its panels, in the most columns (<= ``max_columns``)
    whose width fits the figure; entries fill the columns top to bottom. Handles whose label
    starts with "_" (matplotlib's unlabelled artists) are left out."""
    handles = [h for h in handles if not h.get_label().startswith("_")]
    renderer = FigureCanvasAgg(fig).get_renderer()
    for ncols in range(min(max_columns, len(handles)), 0, -1):
        legend = fig.legend(handles=handles, loc="outside lower center", ncols=ncols)
        if ncols == 1 or legend.get_window_extent(renderer).width <= fig.bbox.width:
            return legend
        legend.remove()
    raise ValueError("no legend entries")


def number(value: float, digits: int = 3) -> str:
    """``value`` as mathtext without the dollars: ``2\\times10^{5}``, ``10^{-4}``, ``0.623``, ``360``.

    Up to ``digits`` significant digits; a power of ten outside ``10^-2 <= abs(value) < 10^4``.
    """
    if value == 0.0 or not math.isfinite(value):
        return f"{value:g}"
    exponent = math.floor(math.log10(abs(value)))
    if -2 <= exponent < 4:
        return f"{value:.{digits}g}"
    mantissa = float(f"{value / 10.0 ** exponent:.{digits}g}")
    if abs(mantissa) >= 10.0:  # rounding carried into the next power
        mantissa, exponent = mantissa / 10.0, exponent + 1
    power = f"10^{{{exponent}}}"
    if mantissa == 1.0:
        return power
    if mantissa == -1.0:
        return "-" + power
    return f"{mantissa:g}\\times{power}"
