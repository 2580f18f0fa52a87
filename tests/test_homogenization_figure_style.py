"""One figure style: the shared tick formatter on every linear axis of every figure function,
mathtext labels, numbers written as mathtext powers of ten."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from cell_doubles import ElasticCell
from homogenization.cli import bvp, sweep
from homogenization.element_test import driver, programme as programmes
from homogenization.output import figure_style, figures
from homogenization.fe import output as fe_output
from homogenization.backends import make_cell_model
from homogenization.output.figure_style import TickFormatter
from warp_hcell.core.cli import run_main
from warp_hcell.mesostructures.hcell import h_cell


@pytest.fixture(scope="module")
def records() -> dict[float, driver.Record]:
    """Analytical runs at p0 = 2e5 and 5.85e6 N/m."""
    return {p0: driver.run(make_cell_model("analytical"), programmes.biaxial(p0, 0.02, 1e-3), mesostructure=h_cell(55.0),
                           n_orientations=12, progress=False) for p0 in (2e5, 5.85e6)}


def linear_axes_use_the_shared_formatter(fig) -> None:
    checked = 0
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() == "linear":
                assert type(axis.get_major_formatter()) is TickFormatter, (ax.get_title(), axis.axis_name)
                checked += 1
    assert checked >= 2


@pytest.fixture(scope="module")
def bvp_figure(tmp_path_factory):
    """The Figure that ``bvp`` writes to bvp.png (a 2 x 4 specimen with the material point)."""
    saved = []
    real = fe_output.make_figure

    def spy(*args, **kwargs):
        saved.append(real(*args, **kwargs))
        return saved[-1]

    mp = pytest.MonkeyPatch()
    mp.setattr(fe_output, "make_figure", spy)
    try:
        out = tmp_path_factory.mktemp("bvp") / "run"
        argv = ["--alpha0", "40", "--p0", "5.85e6", "--eps-max", "0.005", "--increment", "1e-3", "--orientations", "8",
                "--elements", "2,4", "--iso-steps", "3", "--compare", "--out", str(out)]
        assert run_main(bvp.main, argv) == 0
    finally:
        mp.undo()
    assert (out / fe_output.FIGURE_FILE).is_file()
    return saved[0]


def test_biaxial_figures_use_the_shared_formatter(records):
    runs = [figures.Run(record, {"p0": p0, "drained": False}) for p0, record in records.items()]
    for fig in (figures.make_figure({"a": records[2e5]}), figures.make_figure({"a": records[2e5]}, fourth="W2"),
                figures.overlay_figure(runs), figures.overlay_figure(runs, normalise=True)):
        linear_axes_use_the_shared_formatter(fig)


def test_sweep_summary_figure_uses_the_shared_style(records):
    runs = [figures.Run(record, {"p0": p0, "backend": "analytical", "mesostructure": "hcell", "alpha0_deg": 55.0})
            for p0, record in records.items()]
    fig = sweep.make_summary_figure(runs)
    linear_axes_use_the_shared_formatter(fig)
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == [r"$p_0 = 2\times10^{5}$ N/m",
                                                                   r"$p_0 = 5.85\times10^{6}$ N/m"]
    assert fig.get_suptitle().startswith(r"sweep: constant-volume biaxial test, analytical, H-cell, $\alpha_0$ = 55°")
    x, y = fig.axes[2].get_lines()[1].get_data()
    curve = figures.shear_curve(records[5.85e6])
    assert np.allclose(x, curve.p / 5.85e6) and np.allclose(y, curve.q / 5.85e6)


def test_bvp_figure_uses_the_shared_formatter_and_mathtext_labels(bvp_figure):
    linear_axes_use_the_shared_formatter(bvp_figure)
    ax_q, ax_v, ax_m, colour_bar = bvp_figure.axes
    for ax in (ax_q, ax_v, ax_m):
        assert ax.get_xlabel().startswith("$") and ax.get_ylabel().startswith("$")
    assert r"\sigma_{11} - \sigma_{22}" in ax_q.get_ylabel() and r"\varepsilon_v" in ax_v.get_ylabel()
    assert r"\varepsilon_1" in ax_q.get_xlabel() and "[%]" in ax_q.get_xlabel()
    assert r"\varepsilon_d" in colour_bar.get_ylabel()
    assert "s11" not in bvp_figure.get_suptitle() and r"$p_0 = 5.85\times10^{6}$ N/m" in bvp_figure.get_suptitle()
    assert [t.get_text() for t in ax_q.get_legend().get_texts()] == ["finite elements", "material point"]
    assert ax_v.get_legend() is None and not bvp_figure.legends


@pytest.mark.parametrize("p0, power", [(2e5, "10^{5}"), (5.85e6, "10^{6}")])
def test_stress_ticks_carry_a_mathtext_power_of_ten_at_every_p0(records, p0, power):
    fig = figures.make_figure({"": records[p0]})
    FigureCanvasAgg(fig).draw()
    ax_q = fig.axes[0]
    assert power in ax_q.yaxis.get_offset_text().get_text() and r"\times" in ax_q.yaxis.get_offset_text().get_text()
    labels = [t.get_text() for t in ax_q.get_yticklabels()]
    assert labels and not any("000" in text or "e+" in text for text in labels)
    assert fig.axes[3].yaxis.get_offset_text().get_text() == ""  # q/p ~ 1: plain numbers


def test_tick_formatter_writes_small_and_large_numbers_alike():
    from matplotlib.figure import Figure

    assert TickFormatter().get_useMathText() and not TickFormatter().get_useOffset()
    fig = Figure()
    ax_large, ax_small, ax_offset = fig.subplots(1, 3)
    ax_large.plot([0.0, 3e5], [0.0, 1e-4])
    ax_small.plot([0.0, 100.0], [0.0, 1.0])
    ax_offset.plot([0.0, 1.0], [5.85e6, 5.86e6])  # a narrow range far from 0: no additive offset
    figure_style.apply_style(fig)
    FigureCanvasAgg(fig).draw()
    assert "10^{5}" in ax_large.xaxis.get_offset_text().get_text()
    assert "10^{\u22124}" in ax_large.yaxis.get_offset_text().get_text()  # mathtext minus sign
    assert ax_small.xaxis.get_offset_text().get_text() == "" and ax_small.yaxis.get_offset_text().get_text() == ""
    assert r"$\mathdefault{50}$" in [t.get_text() for t in ax_small.get_xticklabels()]
    offset = ax_offset.yaxis.get_offset_text().get_text()
    assert "10^{6}" in offset and "+" not in offset


@pytest.mark.parametrize("value, text", [(2e5, r"2\times10^{5}"), (5.85e6, r"5.85\times10^{6}"), (1e-4, "10^{-4}"),
                                         (0.623, "0.623"), (360.0, "360"), (9.9999e5, "10^{6}"),
                                         (-3e8, r"-3\times10^{8}"), (0.0, "0")])
def test_number_is_mathtext(value, text):
    assert figure_style.number(value) == text


def test_elastic_double_figure_has_a_shared_legend():
    record = driver.run(ElasticCell(), programmes.biaxial(2e5, 0.01, 1e-3), mesostructure=h_cell(), n_orientations=4,
                        progress=False)
    fig = figures.make_figure({"one": record, "two": record})
    assert len(fig.legends) == 1 and [t.get_text() for t in fig.legends[0].get_texts()] == ["one", "two"]
