"""Oedometric (K0) programme of the 3D H-model: lateral strains held at zero, the K0 of an elastic-like
start, the oedometer table and the one-line errors of ``hmodel triaxial --oedometer``."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.cli import hmodel
from homogenization.element_test import driver, programme as programmes
from homogenization.output import io, oedometer
from warp_hcell.mesostructures.builders import mesostructure_arg


def run(programme: programmes.Programme) -> driver.Record:
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    return driver.run(make_cell_model("analytical", dim=3), programme, mesostructure=meso, lebedev_order=5,
                      n_spins=2, staggered_spins=False, progress=False)


def test_oedometric_programme_keeps_the_lateral_strains_and_returns_the_axial_strain():
    programme = programmes.oedometric(2e4, 3e-3, 3e-3, 5e-4, iso_increment=1e-4)
    assert [s.label for s in programme] == ["iso", "load", "unload"]
    record = run(programme)
    seated = np.flatnonzero(record.stage == "iso")[-1]
    after = slice(seated, None)
    assert np.all(record.eps22[after] == record.eps22[seated]) and np.all(record.eps33[after] == record.eps33[seated])
    assert record.eps11[np.flatnonzero(record.stage == "load")[-1]] == pytest.approx(record.eps11[seated] + 3e-3, abs=1e-15)
    assert record.eps11[-1] == pytest.approx(record.eps11[seated], abs=1e-15)
    table = oedometer.columns(record)
    np.testing.assert_allclose(np.diff(table["eps_v"][after]), np.diff(record.eps11[after]), rtol=0, atol=1e-15)
    load = record.stage == "load"
    assert np.all(np.diff(table["sigma_v"][load]) > 0.0) and np.all(np.diff(table["sigma_v"][record.stage == "unload"]) < 0.0)
    np.testing.assert_allclose(table["K0"], table["sigma_h"] / table["sigma_v"], rtol=1e-15)
    assert 0.0 < table["K0"][load].min() and table["K0"][load].max() < 1.0
    assert programmes.oedometric(2e4, 3e-3, 0.0, 5e-4)[-1].label == "load"


def test_k0_of_an_isotropic_start_is_the_superposition_of_uniaxial_strains():
    """Near an isotropic state the closed form is linear: a uniaxial strain d (11) with lateral strains held
    adds d sigma_v + 2 d sigma_h = the stress of an isotropic strain d on every component, so
    1 + 2 K0 = (sigma_iso / d) / (d sigma_v / d) for the incremental K0 = d sigma_h / d sigma_v."""
    d = 1e-5
    record = run((programmes.Step(("strain",) * 3, (d,) * 3, 1, "iso"), programmes.Step(("strain",) * 3, (d, 0.0, 0.0), 1, "load")))
    iso = record.sigma11[0]
    d_v, d_h = record.sigma11[1] - iso, 0.5 * (record.sigma22[1] + record.sigma33[1]) - iso
    k0 = d_h / d_v
    assert 0.2 < k0 < 0.8
    assert (1.0 + 2.0 * k0) * d_v / iso == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("value, bad", [("0.02", "0.02"), ("-1e-3", "-0.001"), ("nan", None)])
def test_oedometer_unloading_outside_the_loading_is_one_line_and_exit_2(tmp_path, capsys, value, bad):
    out = tmp_path / "oed"
    out.mkdir()
    (out / io.CURVE_FILE).write_text("old\n")
    assert hmodel.main(["triaxial", f"--oedometer={value}", "--eps-max", "1e-2", "--overwrite", "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hmodel triaxial: error: "), lines
    if bad is not None:
        assert f"--oedometer {bad}: the unloading strain must be in [0, --eps-max 0.01]" in lines[0]
    assert (out / io.CURVE_FILE).read_text() == "old\n"


def test_oedometer_conflicts_with_a_programme_file_and_other_tests(tmp_path, capsys):
    for argv in (["--programme", str(tmp_path / "p.json")], ["--undrained"]):
        assert hmodel.main(["triaxial", "--oedometer", "0", *argv, "--out", str(tmp_path / "o")]) == 2
        assert len(capsys.readouterr().err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_cli_oedometer_writes_the_table_of_its_curve(tmp_path):
    out = tmp_path / "oed"
    assert hmodel.main(["triaxial", "--oedometer", "1e-3", "--eps-max", "2e-3", "--increment", "5e-4", "--p0", "2e4",
                        "--order", "3", "--spins", "1", "--aligned-spins", "-q", "--out", str(out)]) == 0
    with open(out / oedometer.FILE, newline="") as handle:
        rows = list(csv.DictReader(handle))
    with open(out / io.CURVE_FILE, newline="") as handle:
        curve = list(csv.DictReader(handle))
    assert list(rows[0]) == list(oedometer.COLUMNS) and len(rows) == len(curve)
    assert [r["stage"] for r in rows] == [c["stage"] for c in curve]
    assert {r["stage"] for r in rows} == {"iso", "load", "unload"}
    for row, point in zip(rows, curve):
        s11, s22, s33 = (float(point[k]) for k in ("sigma11", "sigma22", "sigma33"))
        assert float(row["sigma_v"]) == pytest.approx(s11, rel=1e-9)
        assert float(row["K0"]) == pytest.approx(0.5 * (s22 + s33) / s11, rel=1e-8)
        assert float(row["eps_v"]) == pytest.approx(sum(float(point[k]) for k in ("eps11", "eps22", "eps33")), rel=1e-8)


def test_cli_oedometer_reruns_over_its_own_output_with_overwrite(tmp_path):
    argv = ["triaxial", "--oedometer", "0", "--eps-max", "1e-3", "--increment", "5e-4", "--p0", "2e4", "--order", "3",
            "--spins", "1", "-q", "--out", str(tmp_path / "oed")]
    assert hmodel.main(argv) == 0
    assert hmodel.main([*argv, "--overwrite"]) == 0
    assert (tmp_path / "oed" / oedometer.FILE).is_file()
