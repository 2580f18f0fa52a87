"""The 2x2 biaxial figure: curves start at the end of stage 1, labelled axes, overlaid backends."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cell_doubles import ElasticCell
from homogenization.element_test import driver, programme as programmes
from homogenization.output import figures
from homogenization.cli import plot
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell

P0 = 2e5


@pytest.fixture(scope="module")
def runs() -> dict[str, driver.Record]:
    programme = programmes.biaxial(P0, 0.02, 5e-4)
    return {
        "analytical": driver.run(make_cell_model("analytical"), programme, mesostructure=h_cell(55.0), n_orientations=24,
                                 progress=False),
        "elastic": driver.run(ElasticCell(), programme, mesostructure=h_cell(), n_orientations=8, progress=False),
    }


def test_shear_curve_counts_from_end_of_stage_one(runs):
    record = runs["analytical"]
    curve = figures.shear_curve(record)
    n_shear = int(np.sum(record.stage == "shear"))
    assert curve.eps1.shape == (n_shear + 1,) and curve.w2.shape == (n_shear,)
    assert curve.eps1[0] == 0.0 and curve.eps1[-1] == pytest.approx(0.02)
    assert curve.p[0] == pytest.approx(P0, rel=1e-6) and abs(curve.q[0]) <= 1e-9 * P0
    assert np.abs(curve.eps_v).max() <= 1e-15  # constant volume
    assert curve.q[1:].max() > 0.1 * P0


def test_single_stage_record_starts_at_the_initial_state():
    record = driver.run(ElasticCell(), (programmes.proportional_strain(0.01, 0.0, 4),), mesostructure=h_cell(),
                        n_orientations=4, progress=False)
    curve = figures.shear_curve(record)
    assert curve.eps1.tolist() == pytest.approx([0.0, 0.0025, 0.005, 0.0075, 0.01])
    assert curve.p[0] == 0.0


def test_figure_panels_labels_and_overlay(runs, tmp_path):
    fig = figures.make_figure(runs, title="test")
    axes = fig.axes
    assert len(axes) == 4
    assert "[N/m]" in axes[0].get_ylabel() and "q" in axes[0].get_ylabel()
    assert "p = " in axes[1].get_xlabel() and "[N/m]" in axes[1].get_xlabel()
    assert "[%]" in axes[2].get_xlabel() and "[N/m]" in axes[2].get_ylabel()
    assert "q/p" in axes[3].get_ylabel()
    assert all(ax.get_legend() is None for ax in axes)  # one legend for the figure, not one per panel
    assert len(fig.legends) == 1
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["analytical", "elastic"]
    x, y = axes[1].get_lines()[0].get_data()  # Cambridge plane of the analytical run
    curve = figures.shear_curve(runs["analytical"])
    assert np.array_equal(x, curve.p) and np.array_equal(y, curve.q)
    path = figures.save_figure(fig, tmp_path / "cambridge.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_half_deviator_option(runs):
    fig = figures.make_figure(runs, deviator="t")
    curve = figures.shear_curve(runs["analytical"])
    assert fig.axes[0].get_ylabel().startswith("$t = ")
    assert np.array_equal(fig.axes[1].get_lines()[0].get_ydata(), 0.5 * curve.q)
    assert fig.axes[3].get_ylabel() == "$t/p$ [-]"


def test_single_unlabelled_run_has_no_legend(runs):
    fig = figures.make_figure({"": runs["analytical"]}, title="analytical")
    assert not fig.legends and all(ax.get_legend() is None for ax in fig.axes)


def test_drained_and_w2_panels(runs):
    fig = figures.make_figure(runs, drained=True, fourth="W2")
    assert "varepsilon_v" in fig.axes[2].get_ylabel() and "W_2" in fig.axes[3].get_ylabel()
    with pytest.raises(ValueError, match=r"^fourth panel 'x' is not one of \('q/p', 'W2'\)$"):
        figures.make_figure(runs, fourth="x")
    with pytest.raises(ValueError, match=r"^deviator 's' is not one of \('q', 't'\)$"):
        figures.make_figure(runs, deviator="s")
    with pytest.raises(ValueError, match="^nothing to plot: no runs given$"):
        figures.make_figure({})


# -- hmodel plot: overlay finished runs -----------------------------------------------------

def _stored_run(tmp_path, name: str, record: driver.Record, drained: bool) -> str:
    from homogenization.output import io

    path, _ = io.write_run(tmp_path / name, record, parameters={"p0": P0, "drained": drained}, seed=0)
    return str(path)


@pytest.mark.parametrize("suffix, magic", [(".png", b"\x89PNG"), (".pdf", b"%PDF"), (".svg", b"<?xml")])
def test_plot_command_overlays_runs_in_every_format(runs, tmp_path, suffix, magic, capsys):
    from warp_hcell.core.cli import run_main

    files = [_stored_run(tmp_path, name, record, False) for name, record in runs.items()]
    out = tmp_path / f"overlay{suffix}"
    assert run_main(plot.main, [*files, "--out", str(out)]) == 0
    assert out.read_bytes()[:len(magic)] == magic
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_plot_reads_drained_from_the_file(runs, tmp_path, monkeypatch):
    seen = {}
    real = figures.make_figure

    def spy(records, **kwargs):
        seen.update(kwargs)
        return real(records, **kwargs)

    monkeypatch.setattr(figures, "make_figure", spy)
    drained = driver.run(make_cell_model("analytical"), programmes.biaxial(P0, 0.01, 5e-4, drained=True),
                         mesostructure=h_cell(), n_orientations=12, progress=False)
    path = _stored_run(tmp_path, "d", drained, None)  # no drained parameter: read from the programme
    assert plot.main([path, "--out", str(tmp_path / "d.png")]) == 0
    assert seen["drained"] is True
    undrained = _stored_run(tmp_path, "u", runs["analytical"], False)
    assert plot.main([undrained, "--out", str(tmp_path / "u.png")]) == 0
    assert seen["drained"] is False


def test_plot_refuses_bad_suffix_mixed_runs_and_existing_figure(runs, tmp_path, capsys):
    from warp_hcell.core.cli import run_main

    undrained = _stored_run(tmp_path, "u", runs["analytical"], False)
    drained = _stored_run(tmp_path, "d", runs["analytical"], True)
    assert run_main(plot.main, [undrained, "--out", str(tmp_path / "f.jpg")]) == 2
    assert run_main(plot.main, [undrained, drained, "--out", str(tmp_path / "f.png")]) == 2
    existing = tmp_path / "old.png"
    existing.write_bytes(b"keep")
    assert run_main(plot.main, [undrained, "--out", str(existing)]) == 2
    assert existing.read_bytes() == b"keep"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("hmodel: error:") for line in err)


def test_plot_refuses_the_planar_figures_options_for_3d_runs_and_names_a_sweeps_runs(tmp_path, capsys):
    """--csl, --normalise, --deviator and --fourth-panel drew nothing on a 3D run's figure (the same bytes as
    without), and --csl tested its end with planar p, q and eps_v; a sweep's folder named no run."""
    from homogenization.cli import hmodel, sweep
    from warp_hcell.core.cli import run_main

    run = tmp_path / "tx"
    assert hmodel.main(["triaxial", "--order", "11", "--spins", "4", "--p0", "2e5", "--eps-max", "0.005",
                        "--increment", "5e-4", "--out", str(run), "-q"]) == 0
    for flags in (["--csl"], ["--normalise"], ["--deviator", "t"], ["--fourth-panel", "W2"]):
        assert run_main(plot.main, [str(run), *flags, "--out", str(tmp_path / "f.png")]) == 2
        assert f"{flags[0]} apply to planar (biaxial) runs" in capsys.readouterr().err
    assert run_main(plot.main, [str(run), "--out", str(tmp_path / "f.png")]) == 0
    out = tmp_path / "s"
    assert run_main(sweep.main, ["--backend", "analytical", "--orientations", "12", "--eps-max", "0.005",
                                 "--increment", "5e-4", "--workers", "1", "--out", str(out), "-q"]) == 0
    capsys.readouterr()
    assert run_main(plot.main, [str(out), "--out", str(tmp_path / "g.png")]) == 2
    assert f"the runs in it: {next((out / 'cases').iterdir()) / 'run.h5'}" in capsys.readouterr().err


def test_plot_command_prints_nothing_of_folders_and_reports_the_figure(runs, tmp_path, capsys):
    files = [_stored_run(tmp_path, name, record, False) for name, record in runs.items()]
    assert plot.main([*files, "--out", str(tmp_path / "f.png")]) == 0
    assert capsys.readouterr().out.strip() == f"figure -> {tmp_path / 'f.png'}"


# -- labels and titles from the runs' metadata ----------------------------------------------

def _spy_saved_figures(monkeypatch) -> list:
    """Figures passed to ``figures.save_figure`` from now on (they are still written)."""
    saved = []
    real = figures.save_figure

    def spy(fig, path, **kwargs):
        saved.append(fig)
        return real(fig, path, **kwargs)

    monkeypatch.setattr(figures, "save_figure", spy)
    return saved


def _figure_of_plot(monkeypatch, argv) -> tuple[int, object]:
    """Run ``hmodel plot`` and return (exit code, the Figure it saved, or None)."""
    from warp_hcell.core.cli import run_main

    saved = _spy_saved_figures(monkeypatch)
    code = run_main(plot.main, argv)
    return code, saved[-1] if saved else None


def _legend(fig) -> list[str]:
    assert len(fig.legends) <= 1 and all(ax.get_legend() is None for ax in fig.axes)
    return [t.get_text() for t in fig.legends[0].get_texts()] if fig.legends else []


@pytest.fixture(scope="module")
def high(runs) -> driver.Record:
    """The analytical run of ``runs`` at p0 = 5.85e6 N/m."""
    return driver.run(make_cell_model("analytical"), programmes.biaxial(5.85e6, 0.02, 5e-4), mesostructure=h_cell(55.0),
                      n_orientations=24, progress=False)


def _write(folder, record, **parameters) -> str:
    from homogenization.output import io

    path, _ = io.write_run(folder, record, parameters=parameters, seed=0)
    return str(path)


def test_labels_come_from_metadata_not_folders(runs, high, tmp_path, monkeypatch):
    low = {"backend": "analytical", "alpha0_deg": 55.0, "p0": P0, "n_orientations": 24, "drained": False}
    x = _write(tmp_path / "x", runs["analytical"], **low)
    y = _write(tmp_path / "y", high, **(low | {"p0": 5.85e6}))
    code, fig = _figure_of_plot(monkeypatch, [x, y, "--out", str(tmp_path / "f.png")])
    assert code == 0
    assert _legend(fig) == [r"$p_0 = 2\times10^{5}$ N/m", r"$p_0 = 5.85\times10^{6}$ N/m"]
    assert fig.get_suptitle() == (r"constant-volume biaxial test, analytical, H-cell, $\alpha_0$ = 55°, $N$ = 24 "
                                  "(compression positive)")
    # the same files in other folders: the same labels
    moved = [tmp_path / "deep" / "a" / "run.h5", tmp_path / "b" / "run.h5"]
    for source, target in zip((x, y), moved):
        target.parent.mkdir(parents=True)
        target.write_bytes(open(source, "rb").read())
    code, again = _figure_of_plot(monkeypatch, [*map(str, moved), "--out", str(tmp_path / "g.png")])
    assert code == 0 and _legend(again) == _legend(fig) and again.get_suptitle() == fig.get_suptitle()


def test_title_names_every_run_and_legend_only_what_differs(runs, high, tmp_path, monkeypatch):
    common = {"alpha0_deg": 55.0, "n_orientations": 24, "drained": False}
    files = [_write(tmp_path / "a", runs["analytical"], backend="analytical", p0=P0, **common),
             _write(tmp_path / "b", runs["analytical"], backend="dem", p0=P0, **common),
             _write(tmp_path / "c", high, backend="ann", p0=5.85e6, **common)]
    code, fig = _figure_of_plot(monkeypatch, [*files, "--out", str(tmp_path / "f.png")])
    assert code == 0
    assert _legend(fig) == [r"analytical, $p_0 = 2\times10^{5}$ N/m", r"DEM, $p_0 = 2\times10^{5}$ N/m",
                            r"ANN, $p_0 = 5.85\times10^{6}$ N/m"]
    title = fig.get_suptitle()
    assert "p_0" not in title and "DEM" not in title and "analytical" not in title  # they differ between runs
    assert r"$\alpha_0$ = 55°" in title and "H-cell" in title


def test_identical_runs_are_numbered(runs, tmp_path, monkeypatch):
    files = [_write(tmp_path / name, runs["analytical"], backend="analytical", p0=P0) for name in ("x", "y")]
    code, fig = _figure_of_plot(monkeypatch, [*files, "--out", str(tmp_path / "f.png")])
    assert code == 0 and _legend(fig) == ["run 1", "run 2"]


# -- --normalise ---------------------------------------------------------------------------

def test_normalise_divides_stresses_by_each_runs_p0(runs, high):
    low_run = figures.Run(runs["analytical"], {"p0": P0, "drained": False})
    high_run = figures.Run(high, {"p0": 5.85e6, "drained": False})
    fig = figures.overlay_figure([low_run, high_run], normalise=True)
    ax_q, ax_pq, ax_p, ax_ratio = fig.axes
    assert ax_pq.get_xlabel().startswith("$p/p_0") and ax_pq.get_ylabel().startswith("$q/p_0")
    assert ax_p.get_ylabel().startswith("$p/p_0") and ax_q.get_ylabel().startswith("$q/p_0")
    for k, (record, p0) in enumerate(((runs["analytical"], P0), (high, 5.85e6))):
        curve = figures.shear_curve(record)
        x, y = ax_pq.get_lines()[k].get_data()
        assert np.allclose(x, curve.p / p0, rtol=1e-14) and np.allclose(y, curve.q / p0, rtol=1e-14)
        assert np.allclose(ax_q.get_lines()[k].get_ydata(), curve.q / p0, rtol=1e-14)
        assert np.allclose(ax_p.get_lines()[k].get_ydata(), curve.p / p0, rtol=1e-14)
        ratio = ax_ratio.get_lines()[k].get_ydata()[1:]
        assert np.allclose(ratio, curve.q[1:] / curve.p[1:], rtol=1e-12)  # q/p is not divided again
    assert x[0] == pytest.approx(1.0, rel=1e-6)  # every curve starts at p = p0
    plain = figures.overlay_figure([low_run, high_run])
    assert np.array_equal(plain.axes[1].get_lines()[1].get_xdata(), figures.shear_curve(high).p)
    assert plain.axes[1].get_xlabel().startswith("$p = ")


def test_normalise_reads_p0_from_the_programme_and_refuses_runs_without(runs, tmp_path, monkeypatch, capsys):
    no_p0 = _write(tmp_path / "a", runs["analytical"])  # no p0 parameter: the programme's stop_at_p
    code, fig = _figure_of_plot(monkeypatch, [no_p0, "--normalise", "--out", str(tmp_path / "f.png")])
    assert code == 0
    assert fig.axes[1].get_lines()[0].get_xdata()[0] == pytest.approx(1.0, rel=1e-6)
    record = driver.run(ElasticCell(), (programmes.proportional_strain(0.01, 0.0, 4),), mesostructure=h_cell(),
                        n_orientations=4, progress=False)
    bare = _write(tmp_path / "b", record)
    code, _ = _figure_of_plot(monkeypatch, [bare, "--normalise", "--out", str(tmp_path / "g.png")])
    assert code == 2 and not (tmp_path / "g.png").exists()
    assert capsys.readouterr().err.strip() == (f"hmodel: error: --normalise: {bare} stores no p0 "
                                               "(no p0 parameter, no stop_at_p step)")


# -- one legend, also for the cyclic programme ---------------------------------------------

CYCLIC = Path(figures.__file__).parents[1] / "data" / "programmes" / "cyclic_constant_volume.toml"


def test_cyclic_programme_figure_has_exactly_one_legend(tmp_path, monkeypatch, capsys):
    programme = programmes.read_programme(CYCLIC)
    files = []
    for name, model, meso in (("analytical", make_cell_model("analytical"), h_cell(55.0)),
                              ("elastic", ElasticCell(), h_cell(55.0))):
        record = driver.run(model, programme, mesostructure=meso, n_orientations=6, progress=False)
        files.append(_write(tmp_path / name, record, backend=name, p0=5.85e6, programme_file=str(CYCLIC)))
    code, fig = _figure_of_plot(monkeypatch, [*files, "--csl", "--out", str(tmp_path / "f.png")])
    assert code == 0
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["analytical", "elastic"]
    assert fig.get_suptitle().startswith("programme cyclic_constant_volume, H-cell")
    captured = capsys.readouterr()
    warnings = captured.err.strip().splitlines()
    assert len(warnings) == 2 and all("no critical-state line: q/p is not stationary" in w for w in warnings)
    assert "critical-state lines: 0 of 2 runs" in captured.out
    assert len(fig.axes[1].get_lines()) == 2  # no line drawn


# -- --csl ---------------------------------------------------------------------------------

M = 0.8


def synthetic(record: driver.Record, p_end: float, slope: float = M) -> driver.Record:
    """``record`` with its shear-stage stresses replaced: p falls from p0 to ``p_end`` over the
    first 60 % of the stage with q = 1.5 slope p, then stays at p_end with q = slope p_end."""
    shear = np.flatnonzero(record.stage == "shear")
    p, q = record.p.copy(), record.q.copy()
    n = shear.size
    s = np.linspace(0.0, 1.0, n)
    p_shear = np.where(s < 0.6, P0 + (p_end - P0) * s / 0.6, p_end)
    q_shear = np.where(s < 0.6, 1.5 * slope * p_shear, slope * p_shear)
    p[shear], q[shear] = p_shear, q_shear
    return dataclasses.replace(record, p=p, q=q, sigma11=p + q / 2.0, sigma22=p - q / 2.0)


def test_csl_slope_is_fitted_to_the_end_of_the_run(runs):
    curve = figures.shear_curve(synthetic(runs["analytical"], 0.5 * P0))
    assert figures.critical_state_slope(curve, P0) == pytest.approx(M, rel=1e-12)
    assert np.polyfit(curve.p, curve.q, 1)[0] != pytest.approx(M, rel=0.05)  # a fit over the whole run is not M


def test_plot_csl_draws_q_equals_m_p_with_m_in_the_legend(runs, tmp_path, monkeypatch):
    files = [_write(tmp_path / "a", synthetic(runs["analytical"], 0.5 * P0), backend="dem", p0=P0),
             _write(tmp_path / "b", synthetic(runs["analytical"], 0.4 * P0, slope=0.6), backend="ann", p0=P0)]
    code, fig = _figure_of_plot(monkeypatch, [*files, "--csl", "--out", str(tmp_path / "f.png")])
    assert code == 0
    lines = fig.axes[1].get_lines()
    assert len(lines) == 4  # two paths, two critical-state lines
    for line, slope in zip((lines[1], lines[3]), (M, 0.6)):
        x, y = line.get_data()
        assert x[0] == 0.0 and y[0] == 0.0 and y[-1] / x[-1] == pytest.approx(slope, rel=1e-12)
    assert _legend(fig) == ["DEM; $M$ = 0.800", "ANN; $M$ = 0.600", "critical-state lines $q = M p$"]
    code, fig = _figure_of_plot(monkeypatch, [files[0], "--csl", "--normalise", "--deviator", "t",
                                              "--out", str(tmp_path / "g.png")])
    x, y = fig.axes[1].get_lines()[1].get_data()
    assert code == 0 and y[-1] / x[-1] == pytest.approx(M / 2.0, rel=1e-12)  # t = M p / 2, over p0 alike
    assert _legend(fig) == ["critical-state line $q = M p$, $M$ = 0.800"]


def test_csl_skips_a_liquefied_run_with_one_warning(runs, tmp_path, monkeypatch, capsys):
    liquefied = synthetic(runs["analytical"], 0.01 * P0)
    with pytest.raises(figures.NoCriticalState, match="liquefied"):
        figures.critical_state_slope(figures.shear_curve(liquefied), P0)
    files = [_write(tmp_path / "a", liquefied, backend="dem", p0=P0),
             _write(tmp_path / "b", synthetic(runs["analytical"], 0.5 * P0), backend="ann", p0=P0)]
    code, fig = _figure_of_plot(monkeypatch, [*files, "--csl", "--out", str(tmp_path / "f.png")])
    assert code == 0
    captured = capsys.readouterr()
    assert captured.err.strip() == (f"hmodel plot: warning: {files[0]}: no critical-state line: it ends at p = 0.01 p0 "
                                    "(liquefied): fewer than half of its last 10 % of points have p > 0.05 p0")
    assert "critical-state lines: 1 of 2 runs" in captured.out
    assert len(fig.axes[1].get_lines()) == 3
    assert _legend(fig) == ["DEM", "ANN; $M$ = 0.800", "critical-state lines $q = M p$"]


def test_csl_refuses_an_end_without_deviator(runs):
    """A run that ends steady at q = 0 (p, q and the volume steady) was called a critical state with M = 0."""
    with pytest.raises(figures.NoCriticalState, match=r"not sheared: abs\(q/p\) falls to 0 < 0.02"):
        figures.critical_state(figures.shear_curve(synthetic(runs["analytical"], 0.5 * P0, slope=0.0)), P0)
    assert figures.critical_state(figures.shear_curve(synthetic(runs["analytical"], 0.5 * P0, slope=-0.5)),
                                  P0).slope == pytest.approx(-0.5, rel=1e-12)  # in extension: M < 0


def test_csl_is_drawn_with_its_rates_where_the_run_reached_a_steady_state(runs, tmp_path, monkeypatch, capsys):
    """The synthetic run holds p, q and the volume steady over its last 40 %: a line, M and the rates reported."""
    steady = _write(tmp_path / "a", synthetic(runs["analytical"], 0.5 * P0), backend="dem", p0=P0)
    state = figures.critical_state(figures.shear_curve(synthetic(runs["analytical"], 0.5 * P0)), P0)
    assert state.slope == pytest.approx(M, rel=1e-12)
    assert state.p_rate <= 1e-9 and state.q_rate <= 1e-9 and state.v_rate <= 1e-12
    assert state.eps1_span[1] == pytest.approx(0.02) and state.eps1_span[0] == pytest.approx(0.018, abs=6e-4)
    code, fig = _figure_of_plot(monkeypatch, [steady, "--csl", "--out", str(tmp_path / "f.png")])
    assert code == 0 and len(fig.axes[1].get_lines()) == 2
    out = capsys.readouterr().out
    assert f"{steady}: M = 0.800 at a critical state over eps1 = " in out
    assert "|dp/deps1|/p = " in out and "(limits 0.1, 0.1, 0.01)" in out


def _loose_undrained(eps_max: float) -> driver.Record:
    return driver.run(make_cell_model("analytical"), programmes.biaxial(P0, eps_max, 1e-3), mesostructure=h_cell(55.0),
                      n_orientations=360, progress=False)


def test_csl_refuses_the_loose_cell_while_p_still_falls(tmp_path, monkeypatch, capsys):
    """alpha0 = 55 deg at 2e5 N/m to 20 %: p/p0 still falls (about 6 % of p per 1 % of eps1) at the end,
    q/p is stationary within 0.1 and p > 0.05 p0: the old rule drew M = 0.14 there; now no line."""
    record = _loose_undrained(0.2)
    curve = figures.shear_curve(record)
    assert 0.05 < curve.p[-1] / P0 < 0.15  # not near the origin, so only the rates can refuse it
    with pytest.raises(figures.NoCriticalState, match=r"p still falling.*: \|dp/deps1\|/p = [0-9.]+ > 0.1"):
        figures.critical_state(curve, P0)
    path = _write(tmp_path / "a", record, backend="analytical", p0=P0)
    code, fig = _figure_of_plot(monkeypatch, [path, "--csl", "--out", str(tmp_path / "f.png")])
    assert code == 0 and len(fig.axes[1].get_lines()) == 1
    captured = capsys.readouterr()
    assert "critical-state lines: 0 of 1 runs" in captured.out
    assert len(captured.err.strip().splitlines()) == 1 and "no critical state reached over eps1 = 18.1-20 %" in captured.err


def test_csl_refuses_a_drained_run_whose_volume_still_changes(runs):
    """A dense drained run at 5.85e6 N/m to 30 %: q/p is stationary (the old rule drew M = 0.66), eps_v is not."""
    record = driver.run(make_cell_model("analytical"), programmes.biaxial(5.85e6, 0.3, 2e-3, drained=True),
                        mesostructure=h_cell(40.0), n_orientations=24, progress=False)
    curve = figures.shear_curve(record)
    with pytest.raises(figures.NoCriticalState, match=r"volume still dilating.*\|deps_v/deps1\| = [0-9.]+ > 0.01"):
        figures.critical_state(curve, 5.85e6)


# -- volumetric strain held at 0 ---------------------------------------------------------------

def _triaxial(test: str) -> driver.Record:
    from warp_hcell.mesostructures.builders import mesostructure_arg

    return driver.run(make_cell_model("analytical", dim=3), programmes.triaxial(2e5, 2e-2, 1e-4, test=test),
                      mesostructure=mesostructure_arg("hcell3d:alpha0=55").build(55.0), lebedev_order=3, n_spins=1,
                      progress=False)


def test_undrained_volume_panel_is_held_at_zero_not_scaled_to_round_off():
    undrained = _triaxial("undrained")
    curve = figures.triaxial_curve(undrained)
    assert 0.0 < np.abs(curve.eps_v).max() < 1e-12  # round-off of 1 - J/J1, not zero
    fig = figures.triaxial_figure({"u": undrained})
    ax = fig.axes[2]
    assert np.array_equal(ax.get_lines()[0].get_ydata(), np.zeros(curve.eps_v.size))
    assert ax.get_ylim() == figures.HELD_AT_ZERO_LIMITS
    assert any("held at 0" in t.get_text() for t in ax.texts)
    fig.canvas.draw()  # tick labels: plain numbers of order 1 %, no factor 10^-11
    labels = [t.get_text() for t in ax.get_yticklabels()] + [ax.yaxis.get_offset_text().get_text()]
    assert not any("10^{-" in label for label in labels)


def test_drained_volume_panel_keeps_its_curve_and_a_mixed_panel_is_not_marked():
    drained, undrained = _triaxial("drained"), _triaxial("undrained")
    curve = figures.triaxial_curve(drained)
    assert np.abs(curve.eps_v).max() > 1e-4
    fig = figures.triaxial_figure({"d": drained, "u": undrained})
    ax = fig.axes[2]
    assert np.allclose(ax.get_lines()[0].get_ydata(), 100.0 * curve.eps_v, rtol=0, atol=1e-14)
    assert np.array_equal(ax.get_lines()[1].get_ydata(), np.zeros(curve.eps_v.size))
    assert not ax.texts and ax.get_ylim() != figures.HELD_AT_ZERO_LIMITS


def test_held_at_zero_threshold():
    eps1 = np.linspace(0.0, 0.15, 16)
    assert figures.held_at_zero(eps1, np.full(16, 1e-10 * 0.15))
    assert not figures.held_at_zero(eps1, np.full(16, 1e-8 * 0.15))


# -- the figure of hmodel biaxial ------------------------------------------------------------

BIAXIAL_TINY = ["--alpha0", "55", "--p0", "2e5", "--eps-max", "0.05", "--increment", "1e-3", "--orientations", "12"]


def test_biaxial_figure_labels_normalise_and_csl(tmp_path, monkeypatch, capsys):
    """The loose cell at 2e5 N/m, 5 % of shear: p still falls, so --csl draws no line and says why."""
    from homogenization.cli import biaxial
    from homogenization.output import io
    from warp_hcell.core.cli import run_main

    saved = _spy_saved_figures(monkeypatch)
    out = tmp_path / "b"
    argv = BIAXIAL_TINY + ["--backend", "analytical", "--normalise", "--csl", "--out", str(out)]
    assert run_main(biaxial.main, argv) == 0
    assert (out / "cambridge.png").is_file()
    fig = saved[0]
    assert fig.get_suptitle() == (r"constant-volume biaxial test, analytical, H-cell, $\alpha_0$ = 55°, "
                                  r"$p_0 = 2\times10^{5}$ N/m, $N$ = 12 (compression positive)")
    assert fig.axes[1].get_xlabel().startswith("$p/p_0")
    assert fig.axes[1].get_lines()[0].get_xdata()[0] == pytest.approx(1.0, rel=1e-6)
    curve = figures.shear_curve(io.read_run(out / "run.h5").record)
    with pytest.raises(figures.NoCriticalState, match="p still falling"):
        figures.critical_state(curve, 2e5)
    assert len(fig.axes[1].get_lines()) == 1 and _legend(fig) == []
    captured = capsys.readouterr()
    assert "(critical-state lines: 0 of 1 runs)" in captured.out
    (warning,) = [line for line in captured.err.splitlines() if "warning" in line]  # the rest: progress bars
    assert warning.startswith("hmodel biaxial: warning: analytical: no critical-state line: no critical state reached")


def test_biaxial_normalise_needs_a_p0(tmp_path, capsys):
    from homogenization.cli import biaxial
    from warp_hcell.core.cli import run_main

    programme = tmp_path / "no_p0.json"
    programme.write_text('{"steps": [{"label": "path", "control": ["strain", "strain"], "target": [0.01, 0.0], '
                         '"n_increments": 10}]}')
    out = tmp_path / "b"
    assert run_main(biaxial.main, ["--programme", str(programme), "--normalise", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == "hmodel: error: --normalise needs p0: the programme has no stop_at_p step"
    assert not out.exists()


def test_a_triaxial_run_is_named_by_its_test_and_its_stresses_in_pa(tmp_path, monkeypatch):
    """hmodel plot of a 3D run: the title names the triaxial test it stores, p0 in Pa (not a biaxial test in N/m)."""
    from warp_hcell.mesostructures.builders import mesostructure_arg

    record = driver.run(make_cell_model("analytical", dim=3), programmes.triaxial(2e5, 2e-3, 5e-4, test="drained"),
                        mesostructure=mesostructure_arg("hcell3d:alpha0=55").build(55.0), lebedev_order=3, n_spins=1,
                        progress=False)
    path = _write(tmp_path / "t", record, backend="analytical", alpha0_deg=55.0, p0=2e5, test="drained")
    code, fig = _figure_of_plot(monkeypatch, [path, "--out", str(tmp_path / "t.png")])
    assert code == 0
    assert fig.get_suptitle().startswith(r"drained triaxial compression, analytical, ")
    assert r"$p_0 = 2\times10^{5}$ Pa" in fig.get_suptitle() and "N/m" not in fig.get_suptitle()
