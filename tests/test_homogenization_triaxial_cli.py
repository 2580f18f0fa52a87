"""hmodel triaxial: the output files (curve.csv header, run.h5 round trip, figure) and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from homogenization.output import io
from homogenization.cli import hmodel, triaxial

FAST = ["--order", "3", "--spins", "1", "--eps-max", "1e-3", "--increment", "2e-4", "--p0", "2e5", "-q"]


@pytest.fixture(scope="module")
def undrained(tmp_path_factory):
    """Output folder of one short undrained run (shared by the tests that read it)."""
    out = tmp_path_factory.mktemp("triaxial") / "tx"
    assert hmodel.main(["triaxial", "--mesostructure", "hcell3d:alpha0=55", "--undrained", *FAST, "--aligned-spins",
                        "--out", str(out)]) == 0
    return out


def test_undrained_run_writes_the_3d_curve_run_file_and_figure(undrained):
    out = undrained
    lines = (out / io.CURVE_FILE).read_text().splitlines()
    assert lines[0] == "stage,eps11,eps22,eps33,sigma11,sigma22,sigma33,p,q,e"
    stages = {line.split(",")[0] for line in lines[1:]}
    assert stages == {"iso", "shear"}
    rows = np.array([[float(v) for v in line.split(",")[1:]] for line in lines[1:]])
    e11, e22, e33, s11, s22, s33, p, q, e = rows.T
    np.testing.assert_allclose(p, (s11 + s22 + s33) / 3.0, rtol=1e-12)
    np.testing.assert_allclose(q, np.abs(s11 - s22), rtol=1e-6, atol=1e-6 * p.max())  # s22 = s33: aligned spins
    stored = io.read_run(out / io.RUN_FILE)
    record = stored.record
    assert record.dim == 3 and record.frames.shape == (record.weights.size, 3, 3)
    np.testing.assert_array_equal(record.eps33, e33)
    assert stored.attrs["V0_units"] == "m^3" and stored.attrs["parameters"]["test"] == "undrained"
    assert stored.attrs["parameters"]["staggered_spins"] is False
    assert json.loads(json.dumps(stored.attrs["programme"]))["steps"][1]["control"] == ["strain"] * 3
    assert (out / triaxial.FIGURE_FILE).stat().st_size > 0


@pytest.mark.parametrize("argv, expected", [
    (["--mesostructure", "hcell:alpha0=55"], "--mesostructure hcell:alpha0=55: a planar cell"),
    (["--eps-max", "1e-3", "--increment", "1e-2"], "--increment 0.01 is larger than --eps-max 0.001"),
    (["--programme", "PLANAR", "--p0", "1e5"], "--p0 do not apply with --programme"),
    (["--programme", "PLANAR"], "its steps control two components (a biaxial programme)"),
    (["--drained", "--extension"], "argument --extension: not allowed with argument --drained"),
    (["--true", "1.5"], "argument --true: b = 1.5 must be in [0, 1]"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, expected):
    planar = tmp_path / "planar.json"
    planar.write_text(json.dumps({"steps": [{"control": ["strain", "strain"], "target": [1e-3, 1e-3],
                                             "n_increments": 10, "label": "iso"}]}))
    argv = [str(planar) if a == "PLANAR" else a for a in argv]
    out = tmp_path / "out"
    assert hmodel.main(["triaxial", *argv, "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hmodel triaxial: error: ") and expected in lines[0], lines
    assert not out.exists()


def test_existing_output_is_kept_without_overwrite(tmp_path, capsys):
    out = tmp_path / "tx"
    out.mkdir()
    (out / io.CURVE_FILE).write_text("old\n")
    assert hmodel.main(["triaxial", *FAST, "--out", str(out)]) == 2
    assert len(capsys.readouterr().err.splitlines()) == 1
    assert (out / io.CURVE_FILE).read_text() == "old\n"


def test_hmodel_plot_draws_3d_runs_in_the_triaxial_panels_and_refuses_a_mix(undrained, tmp_path, capsys):
    out = undrained
    figure = tmp_path / "again.png"
    assert hmodel.main(["plot", str(out / io.RUN_FILE), "--out", str(figure), "-q"]) == 0
    assert figure.stat().st_size > 0
    planar = tmp_path / "bx"
    assert hmodel.main(["biaxial", "--orientations", "6", "--eps-max", "1e-3", "--increment", "2e-4", "-q",
                        "--out", str(planar)]) == 0
    capsys.readouterr()
    assert hmodel.main(["plot", str(out / io.RUN_FILE), str(planar / io.RUN_FILE), "--out", str(tmp_path / "m.png")]) == 2
    assert "mix planar (biaxial) and 3D (triaxial) runs" in capsys.readouterr().err
