"""Density as the state: the void-ratio map (homogenization.material.density), its round trip and bounds."""

import json
import math

import numpy as np
import pytest

from homogenization.material import density
from homogenization.material.density import DensityMap, default_map
from warp_hcell.core.errors import UserError


@pytest.mark.parametrize("dim", [2, 3])
def test_the_map_ends_at_the_densest_and_loosest_cells_and_round_trips(dim):
    m = default_map(dim, 0.55, 0.95)
    dense, loose = density.OPENING_RANGE_DEG[dim]
    assert m.alpha0_deg(0.55) == pytest.approx(dense, abs=1e-12)
    assert m.alpha0_deg(0.95) == pytest.approx(loose, abs=1e-12)
    assert m.alpha0_deg(0.75) == pytest.approx(0.5 * (dense + loose), abs=1e-12)  # linear in alpha0
    for e in np.linspace(0.55, 0.95, 9):
        assert m.void_ratio(m.alpha0_deg(e)) == pytest.approx(e, abs=1e-12)
    assert m.alpha0_deg(0.6) < m.alpha0_deg(0.9)  # denser: smaller opening


@pytest.mark.parametrize("e", [0.5, 1.0, -0.1, math.nan, math.inf])
def test_a_void_ratio_outside_the_map_is_one_line(e):
    with pytest.raises(UserError) as info:
        default_map(2, 0.55, 0.95).alpha0_deg(e)
    assert "\n" not in str(info.value)


def test_bad_maps_and_angles_are_refused():
    for args in ((0.9, 0.5, 40.0, 60.0), (-0.1, 0.5, 40.0, 60.0), (0.5, 0.9, 60.0, 40.0), (0.5, 0.9, 20.0, 60.0)):
        with pytest.raises(ValueError):
            DensityMap(*args)
    m = default_map(2, 0.6, 1.0)  # beyond its angles: the line extended, and said so by contains
    assert m.void_ratio(35.0) == pytest.approx(0.6 - 5.0 / (56.0 - 40.0) * 0.4) and not m.contains(35.0)
    assert DensityMap.from_dict(default_map(3).to_dict()) == default_map(3)


def test_the_array_rule_is_nan_outside_each_sets_range():
    alpha = density.opening_angle_deg(0.7, np.array([0.5, 0.75, 0.6]), np.array([0.9, 0.9, 0.6]), 40.0, 60.0)
    assert alpha[0] == pytest.approx(50.0) and np.isnan(alpha[1]) and np.isnan(alpha[2])


def test_current_void_ratio_and_the_default_e0_of_an_alpha0():
    # contraction (J < 1) lowers e: 1 + e is proportional to the volume
    assert density.current_void_ratio(0.8, [1.0, 0.9]) == pytest.approx([0.8, 0.62])
    m = default_map(2)
    assert density.initial_void_ratio(55.0, 2) == pytest.approx(m.void_ratio(55.0))
    assert math.isnan(density.initial_void_ratio(35.0, 2)) and math.isnan(density.initial_void_ratio(None, 3))


# --- the commands: --void-ratio, the e column, the run file, bad input -------------------------------------------

import csv  # noqa: E402

import h5py  # noqa: E402

from homogenization.cli import hmodel  # noqa: E402
from homogenization.output import io  # noqa: E402

FAST_2D = ["--orientations", "12", "--eps-max", "0.01", "--increment", "1e-3", "--p0", "2e5", "-q"]
FAST_3D = ["--order", "3", "--spins", "1", "--eps-max", "2e-3", "--increment", "5e-4", "--p0", "2e5", "-q"]


def read_curve(path):
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    return {name: np.array([float(r[name]) for r in rows]) for name in rows[0] if name != "stage"}


def volume_ratio_from_strains(curve, dim):
    """J = V / V0 rebuilt from the curve's strains alone: each increment scales every normal length by
    (1 - d_eps) (compression positive), so J is the product over increments and components."""
    normals = [curve[f"eps{c}{c}"] for c in "123"[:dim]]
    factor = np.ones(normals[0].size)
    for eps in normals:
        factor = factor * (1.0 - np.diff(eps, prepend=0.0))
    return np.cumprod(factor)


@pytest.mark.parametrize("dim, command, fast, e0", [(2, "biaxial", FAST_2D, 0.70), (3, "triaxial", FAST_3D, 0.90)])
def test_the_e_column_is_the_given_void_ratio_carried_by_the_volume(tmp_path, dim, command, fast, e0):
    out = tmp_path / command
    assert hmodel.main([command, "--void-ratio", str(e0), "--e-min", "0.55", "--e-max", "0.95", *fast,
                        "--out", str(out)]) == 0
    curve = read_curve(out / io.CURVE_FILE)
    expected = (1.0 + e0) * volume_ratio_from_strains(curve, dim) - 1.0
    np.testing.assert_allclose(curve["e"], expected, rtol=0.0, atol=1e-12)
    assert curve["e"][-1] != pytest.approx(e0, abs=1e-6)  # the strain moved it
    stored = io.read_run(out / io.RUN_FILE)
    density_map = default_map(dim, 0.55, 0.95)
    assert stored.record.e0 == e0 and stored.record.density_map == density_map
    assert stored.attrs["alpha0_deg"] == pytest.approx(density_map.alpha0_deg(e0), abs=1e-9)
    assert stored.attrs["parameters"]["void_ratio"] == e0
    assert stored.attrs["parameters"]["density_map"] == density_map.to_dict()


def test_a_run_given_alpha0_gets_e0_from_the_default_map_or_nan_outside_it(tmp_path):
    out = tmp_path / "a55"
    assert hmodel.main(["biaxial", "--alpha0", "55", *FAST_2D, "--out", str(out)]) == 0
    curve = read_curve(out / io.CURVE_FILE)
    e0 = default_map(2).void_ratio(55.0)
    np.testing.assert_allclose(curve["e"], (1 + e0) * volume_ratio_from_strains(curve, 2) - 1, atol=1e-12)
    with h5py.File(out / io.RUN_FILE, "r") as f:
        assert f.attrs["void_ratio"] == pytest.approx(e0) and not f.attrs["void_ratio_given"]
        assert json.loads(f.attrs["density_map"]) == default_map(2).to_dict()
    out = tmp_path / "a35"
    assert hmodel.main(["biaxial", "--alpha0", "35", *FAST_2D, "--out", str(out)]) == 0
    assert np.all(np.isnan(read_curve(out / io.CURVE_FILE)["e"]))
    with h5py.File(out / io.RUN_FILE, "r") as f:
        assert np.isnan(f.attrs["void_ratio"]) and json.loads(f.attrs["density_map"]) is None


def test_a_run_file_without_the_void_ratio_still_reads(tmp_path):
    out = tmp_path / "run"
    assert hmodel.main(["biaxial", "--void-ratio", "0.8", *FAST_2D, "--out", str(out)]) == 0
    with h5py.File(out / io.RUN_FILE, "a") as f:  # as written before the void ratio was recorded
        for name in ("void_ratio", "void_ratio_given", "density_map"):
            del f.attrs[name]
    record = io.read_run(out / io.RUN_FILE).record
    assert record.e0 is None and record.density_map is None
    assert record.initial_void_ratio == pytest.approx(default_map(2).void_ratio(record.parameters["alpha0_deg"]))


@pytest.mark.parametrize("command", ["biaxial", "triaxial"])
@pytest.mark.parametrize("flags, expected", [
    (["--void-ratio", "1.2"], "outside the void ratio map"),
    (["--void-ratio", "-0.2"], "a void ratio is a finite number >= 0"),
    (["--void-ratio", "0.7", "--alpha0", "50"], "not both"),
    (["--e-max", "0.9"], "apply with --void-ratio only"),
    (["--void-ratio", "0.7", "--e-min", "0.8", "--e-max", "0.6"], "e_min < e_max"),
    (["--void-ratio", "0.7", "--mesostructure", "hcell3d:alpha0=55"], "fixes its own"),
])
def test_bad_void_ratios_are_one_line_before_any_run_and_keep_the_output(tmp_path, capsys, command, flags, expected):
    out = tmp_path / "kept"
    out.mkdir()
    (out / io.CURVE_FILE).write_text("old\n")
    fast = FAST_2D if command == "biaxial" else FAST_3D
    assert hmodel.main([command, *flags, *fast, "--overwrite", "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"hmodel {command}: error: ") and expected in lines[0], lines
    assert (out / io.CURVE_FILE).read_text() == "old\n" and sorted(p.name for p in out.iterdir()) == [io.CURVE_FILE]


def test_dense_dilates_and_loose_contracts_when_drained(tmp_path):
    """One map, two densities: the densest end of the map dilates, the loosest contracts (2D closed form)."""
    eps_v = {}
    for e0 in (0.62, 0.95):
        out = tmp_path / str(e0)
        assert hmodel.main(["biaxial", "--void-ratio", str(e0), "--drained", "--orientations", "36", "--eps-max", "0.05",
                            "--increment", "1e-3", "--p0", "2e5", "-q", "--out", str(out)]) == 0
        curve = read_curve(out / io.CURVE_FILE)
        eps_v[e0] = curve["eps11"][-1] + curve["eps22"][-1]
        assert (curve["e"][-1] > e0) == (eps_v[e0] < 0)  # e rises where the sample dilates
    assert eps_v[0.62] < -0.005 and eps_v[0.95] > 0.001


# --- calibration: '# void_ratio = E' in a data file's header -------------------------------------------------------

from homogenization.calibration.data import read_test  # noqa: E402


def write_data(path, void_ratio=None, test="drained"):
    lines = [f"# test = {test}", "# p0 = 2e5"] + ([f"# void_ratio = {void_ratio}"] if void_ratio is not None else [])
    path.write_text("\n".join(lines + ["eps1,q", "0.001,1e4", "0.002,2e4"]) + "\n")
    return path


def test_the_calibration_header_gives_each_file_its_void_ratio(tmp_path):
    assert read_test(write_data(tmp_path / "a.csv", "0.72")).void_ratio == 0.72
    assert read_test(write_data(tmp_path / "b.csv")).void_ratio is None
    for bad in ("-0.1", "loose", "nan"):
        with pytest.raises(ValueError, match="void_ratio") as info:
            read_test(write_data(tmp_path / "c.csv", bad))
        assert "\n" not in str(info.value)


from dataclasses import replace  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.forward import ForwardSettings, check_density, simulate, with_density  # noqa: E402

QUICK = ForwardSettings(n_orientations=12, increment=2e-3, iso_increment=1e-3)


@pytest.mark.parametrize("dim, test", [(2, "drained"), (3, "triaxial_drained")])
def test_a_test_with_a_void_ratio_runs_each_set_at_its_maps_alpha0(tmp_path, dim, test):
    measured = read_test(write_data(tmp_path / "d.csv", "0.7", test))
    measured = replace(measured, eps1=np.array([0.002, 0.004, 0.006]))
    sets = {"e_min": np.array([0.5, 0.6, 0.72]), "e_max": np.array([0.9, 1.0, 1.2])}
    settings = with_density(replace(QUICK, lebedev_order=3, n_spins=1), [measured], 0.5, 0.9)
    curves = simulate(measured, sets, settings)
    dense, loose = density.OPENING_RANGE_DEG[dim]
    for i in range(2):  # by hand: alpha0 linear in e between (e_min, dense) and (e_max, loose)
        alpha0 = dense + (0.7 - sets["e_min"][i]) / (sets["e_max"][i] - sets["e_min"][i]) * (loose - dense)
        plain = simulate(replace(measured, void_ratio=None), {"alpha0": np.array([alpha0])}, settings)
        np.testing.assert_allclose(curves.q[i], plain.q[0], rtol=1e-9)
        np.testing.assert_allclose(curves.eps_v[i], plain.eps_v[0], rtol=1e-9, atol=1e-15)
    assert np.all(np.isnan(curves.q[2]))  # e_min = 0.72 > 0.7: this set's map cannot hold the test
    assert not np.allclose(curves.q[0], curves.q[1])


def test_calibration_inputs_the_map_cannot_serve_are_refused(tmp_path):
    given = read_test(write_data(tmp_path / "a.csv", "0.7"))
    plain = read_test(write_data(tmp_path / "b.csv"))
    settings = with_density(QUICK, [given], 0.6, 0.9)
    assert with_density(QUICK, [plain], 0.6, 0.9) == QUICK  # no void ratio: the settings of before
    bounds = forward.DENSITY_PRIOR
    check_density([given, plain], ["e_min", "e_max", "alpha0"], settings, bounds)  # alpha0 serves the plain test
    for tests, params, fixed, match in (
            ([plain], ["e_min"], (0.6, 0.9), "no --data file gives its void ratio"),
            ([given], ["alpha0"], (0.6, 0.9), "calibrate e_min,e_max instead"),
            ([given], ["phi_g"], (0.75, 0.9), "outside what the void-ratio map reaches"),
            ([given], ["phi_g"], (0.5, 0.65), r"reaches, \[0.5, 0.65\]"),
            ([given], ["phi_g"], (0.9, 0.6), "must be below"),
    ):
        with pytest.raises(ValueError, match=match):
            check_density(tests, params, with_density(QUICK, tests, *fixed), bounds)
    far = read_test(write_data(tmp_path / "c.csv", "1.5"))
    with pytest.raises(ValueError, match=r"reaches, \[0.3, 1.4\]"):
        check_density([far], ["e_min", "e_max"], with_density(QUICK, [far], 0.6, 0.9), bounds)


def test_hmodel_calibrate_refuses_an_unreachable_void_ratio_before_any_run(tmp_path, capsys):
    data = write_data(tmp_path / "loose.csv", "1.1")
    out = tmp_path / "cal"
    assert hmodel.main(["calibrate", "--data", str(data), "--params", "phi_g", "--out", str(out), "-q"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "void_ratio = 1.1 is outside" in lines[0] and not out.exists()


def test_the_python_api_records_the_void_ratio_of_a_cell_built_at_the_maps_alpha0():
    from homogenization.backends import make_cell_model
    from homogenization.element_test import driver, programme as programmes
    from warp_hcell.mesostructures.hcell import h_cell

    m = default_map(2, 0.55, 0.95)
    run = dict(n_orientations=6, progress=False)
    record = driver.run(make_cell_model("analytical"), programmes.biaxial(2e5, 2e-3, 1e-3), void_ratio=0.8,
                        density_map=m, mesostructure=h_cell(m.alpha0_deg(0.8)), **run)
    assert record.e0 == 0.8 and record.density_map == m and record.e[0] < 0.8  # isotropic compression
    with pytest.raises(ValueError, match="maps to alpha0"):
        driver.run(make_cell_model("analytical"), programmes.biaxial(2e5, 2e-3, 1e-3), void_ratio=0.8,
                   mesostructure=h_cell(m.alpha0_deg(0.8)), **run)  # the default map gives 0.8 another angle
    with pytest.raises(UserError):
        driver.run(make_cell_model("analytical"), programmes.biaxial(2e5, 2e-3, 1e-3), void_ratio=1.5,
                   mesostructure=h_cell(55.0), **run)
