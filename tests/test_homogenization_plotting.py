"""The 2x2 biaxial figure: curves start at the end of stage 1, labelled axes, overlaid backends."""

from __future__ import annotations

import numpy as np
import pytest

from cell_doubles import ElasticCell
from homogenization import driver, loading, plotting
from homogenization.backends import make_cell_model
from warp_hcell.mesostructure import h_cell

P0 = 2e5


@pytest.fixture(scope="module")
def runs() -> dict[str, driver.Record]:
    programme = loading.biaxial(P0, 0.02, 5e-4)
    return {
        "analytical": driver.run(make_cell_model("analytical"), programme, mesostructure=h_cell(55.0), n_orientations=24,
                                 progress=False),
        "elastic": driver.run(ElasticCell(), programme, mesostructure=h_cell(), n_orientations=8, progress=False),
    }


def test_shear_curve_counts_from_end_of_stage_one(runs):
    record = runs["analytical"]
    curve = plotting.shear_curve(record)
    n_shear = int(np.sum(record.stage == "shear"))
    assert curve.eps1.shape == (n_shear + 1,) and curve.w2.shape == (n_shear,)
    assert curve.eps1[0] == 0.0 and curve.eps1[-1] == pytest.approx(0.02)
    assert curve.p[0] == pytest.approx(P0, rel=1e-6) and abs(curve.q[0]) <= 1e-9 * P0
    assert np.abs(curve.eps_v).max() <= 1e-15  # constant volume
    assert curve.q[1:].max() > 0.1 * P0


def test_single_stage_record_starts_at_the_initial_state():
    record = driver.run(ElasticCell(), (loading.proportional_strain(0.01, 0.0, 4),), mesostructure=h_cell(),
                        n_orientations=4, progress=False)
    curve = plotting.shear_curve(record)
    assert curve.eps1.tolist() == pytest.approx([0.0, 0.0025, 0.005, 0.0075, 0.01])
    assert curve.p[0] == 0.0


def test_figure_panels_labels_and_overlay(runs, tmp_path):
    fig = plotting.make_figure(runs, title="test")
    axes = fig.axes
    assert len(axes) == 4
    assert "[N/m]" in axes[0].get_ylabel() and "q" in axes[0].get_ylabel()
    assert "p = " in axes[1].get_xlabel() and "[N/m]" in axes[1].get_xlabel()
    assert "[%]" in axes[2].get_xlabel() and "[N/m]" in axes[2].get_ylabel()
    assert "q/p" in axes[3].get_ylabel()
    for ax in axes:
        assert [t.get_text() for t in ax.get_legend().get_texts()] == ["analytical", "elastic"]
    x, y = axes[1].get_lines()[0].get_data()  # Cambridge plane of the analytical run
    curve = plotting.shear_curve(runs["analytical"])
    assert np.array_equal(x, curve.p) and np.array_equal(y, curve.q)
    path = plotting.save_figure(fig, tmp_path / "cambridge.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_half_deviator_option(runs):
    fig = plotting.make_figure(runs, deviator="t")
    curve = plotting.shear_curve(runs["analytical"])
    assert fig.axes[0].get_ylabel().startswith("$t = ")
    assert np.array_equal(fig.axes[1].get_lines()[0].get_ydata(), 0.5 * curve.q)
    assert fig.axes[3].get_ylabel() == "$t/p$ [-]"


def test_drained_and_w2_panels(runs):
    fig = plotting.make_figure(runs, drained=True, fourth="W2")
    assert "varepsilon_v" in fig.axes[2].get_ylabel() and "W_2" in fig.axes[3].get_ylabel()
    with pytest.raises(ValueError, match=r"^fourth panel 'x' is not one of \('q/p', 'W2'\)$"):
        plotting.make_figure(runs, fourth="x")
    with pytest.raises(ValueError, match=r"^deviator 's' is not one of \('q', 't'\)$"):
        plotting.make_figure(runs, deviator="s")
    with pytest.raises(ValueError, match="^nothing to plot: no runs given$"):
        plotting.make_figure({})


# -- hmodel plot: overlay finished runs -----------------------------------------------------

def _stored_run(tmp_path, name: str, record: driver.Record, drained: bool) -> str:
    from homogenization import io

    path, _ = io.write_run(tmp_path / name, record, parameters={"p0": P0, "drained": drained}, seed=0)
    return str(path)


@pytest.mark.parametrize("suffix, magic", [(".png", b"\x89PNG"), (".pdf", b"%PDF"), (".svg", b"<?xml")])
def test_plot_command_overlays_runs_in_every_format(runs, tmp_path, suffix, magic, capsys):
    from warp_hcell.cli import run_main

    files = [_stored_run(tmp_path, name, record, False) for name, record in runs.items()]
    out = tmp_path / f"overlay{suffix}"
    assert run_main(plotting.main, [*files, "--out", str(out)]) == 0
    assert out.read_bytes()[:len(magic)] == magic
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_plot_reads_drained_from_the_file(runs, tmp_path, monkeypatch):
    seen = {}
    real = plotting.make_figure

    def spy(records, **kwargs):
        seen.update(kwargs)
        return real(records, **kwargs)

    monkeypatch.setattr(plotting, "make_figure", spy)
    drained = driver.run(make_cell_model("analytical"), loading.biaxial(P0, 0.01, 5e-4, drained=True),
                         mesostructure=h_cell(), n_orientations=12, progress=False)
    path = _stored_run(tmp_path, "d", drained, None)  # no drained parameter: read from the programme
    assert plotting.main([path, "--out", str(tmp_path / "d.png")]) == 0
    assert seen["drained"] is True
    undrained = _stored_run(tmp_path, "u", runs["analytical"], False)
    assert plotting.main([undrained, "--out", str(tmp_path / "u.png")]) == 0
    assert seen["drained"] is False


def test_plot_refuses_bad_suffix_mixed_runs_and_existing_figure(runs, tmp_path, capsys):
    from warp_hcell.cli import run_main

    undrained = _stored_run(tmp_path, "u", runs["analytical"], False)
    drained = _stored_run(tmp_path, "d", runs["analytical"], True)
    assert run_main(plotting.main, [undrained, "--out", str(tmp_path / "f.jpg")]) == 2
    assert run_main(plotting.main, [undrained, drained, "--out", str(tmp_path / "f.png")]) == 2
    existing = tmp_path / "old.png"
    existing.write_bytes(b"keep")
    assert run_main(plotting.main, [undrained, "--out", str(existing)]) == 2
    assert existing.read_bytes() == b"keep"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("hmodel: error:") for line in err)
