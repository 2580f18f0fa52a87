"""A spread of initial opening angles in one material point (alpha0_spread,
homogenization.material.opening_spread): the material point it makes, the forward model with and
without it, the calibration's and hmodel triaxial --posterior's use of it and their one-line refusals."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from homogenization.backends.analytical import Analytical3DCell
from homogenization.calibration import bayes, forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import SPREAD, ForwardSettings, simulate
from homogenization.cli import calibrate, hmodel
from homogenization.element_test.points import orientation_set
from homogenization.material import opening_spread
from homogenization.material.homogenised import HomogenisedMaterial
from homogenization.output import io
from warp_hcell.core.cli import run_main
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.hcell import build_h_cell_3d

SETS = {"phi_g": np.array([30.0, 36.0]), "kn": np.array([2e7, 1.5e7]), "kt_over_kn": np.array([0.5, 0.9]),
        "alpha0": np.array([60.0, 52.0])}
SETTINGS = ForwardSettings(increment=4e-3, iso_increment=2e-3, lebedev_order=5, n_spins=2)
EPS1 = np.linspace(0.004, 0.04, 10)


def drained(path: Path = Path("t.csv")) -> Measurement:
    return Measurement("t", path, True, 1e5, EPS1, {}, 3)


def test_nodes_are_a_uniform_distribution_on_minus_one_one():
    x, g = opening_spread.nodes()
    assert x.size == g.size == opening_spread.N_NODES
    assert g.sum() == pytest.approx(1.0, abs=1e-15) and np.all(np.abs(x) < 1.0)
    # Gauss-Legendre: exact moments of U(-1, 1) up to degree 2 N - 1
    for k in range(2 * opening_spread.N_NODES):
        assert g @ x**k == pytest.approx((1.0 / (k + 1)) if k % 2 == 0 else 0.0, abs=1e-14)


def test_without_a_spread_the_forward_model_is_the_single_alpha0_one_bit_for_bit():
    plain = simulate(drained(), SETS, SETTINGS)
    fixed_zero = simulate(drained(), SETS, ForwardSettings(**{**SETTINGS.__dict__,
                                                               "fixed": {**SETTINGS.fixed, SPREAD: 0.0}}))
    for c in ("q", "p", "eps_v"):
        assert np.array_equal(plain.channel(c), fixed_zero.channel(c), equal_nan=True)
    # a calibrated spread of 0: three identical families, the same curves to round-off
    zero = simulate(drained(), {**SETS, SPREAD: np.zeros(2)}, SETTINGS)
    np.testing.assert_allclose(zero.q, plain.q, rtol=1e-11, atol=1e-6)
    np.testing.assert_allclose(zero.eps_v, plain.eps_v, rtol=0, atol=1e-12)
    # and a spread changes them
    spread = simulate(drained(), {**SETS, SPREAD: np.array([6.0, 5.0])}, SETTINGS)
    assert np.max(np.abs(spread.q - plain.q)) > 1e-2 * np.max(plain.q)


def test_a_spread_point_is_the_volume_weighted_mean_of_single_alpha0_points():
    """sigma = sum_j g_j M_j / sum_j g_j V_j: each family's stress weighted by g_j V0_j (module docstring)."""
    meso = build_h_cell_3d(60.0, radius=0.5)
    orient = orientation_set(meso, n_orientations=1, lebedev_order=3, n_spins=1)
    n = orient.n_cells
    alpha0, spread, kn, kt, phi = 55.0, 6.0, 2e7, 0.6, 30.0
    cells = opening_spread.cell_alpha0(np.array([alpha0]), np.array([spread]), n)
    ones = np.ones(cells.size)
    mixed = HomogenisedMaterial(Analytical3DCell.with_cell_laws(kn * ones, kt * ones, phi * ones, 0.5, alpha0_deg=cells),
                                  opening_spread.replicate(orient), meso, 1)
    x, g = opening_spread.nodes()
    singles = [HomogenisedMaterial(Analytical3DCell(ContactLaw(kn=kn, kt_over_kn=kt, phi_g_deg=phi), 0.5), orient,
                                     build_h_cell_3d(alpha0 + spread * xj, radius=0.5), 1) for xj in x]
    states = [m.init_state() for m in (mixed, *singles)]
    V0 = np.array([m.V0[0] for m in singles])
    assert mixed.V0[0] == pytest.approx(g @ V0, rel=1e-13)
    steps = [np.array([1e-3, 1e-3, 1e-3, 0, 0, 0])] * 3 + [np.array([2e-3, -5e-4, -5e-4, 0, 0, 0])] * 15
    for d_e in steps:
        updates = [m.update(s, d_e[None, :], with_tangent=False) for m, s in zip((mixed, *singles), states)]
        states = [u.state for u in updates]
        weighted = sum(gj * v * u.stress[0] for gj, v, u in zip(g, V0, updates[1:])) / (g @ V0)
        np.testing.assert_allclose(updates[0].stress[0], weighted, rtol=1e-11, atol=1e-9 * np.abs(weighted).max())
    # the families differ (the test is not of three equal points)
    assert np.ptp([u.stress[0, 0] for u in updates[1:]]) > 1e-3 * abs(updates[1].stress[0, 0])


@pytest.mark.parametrize("alpha0, spread, message", [(55.0, -1.0, "must be >= 0"), (50.0, 6.0, "below 45 deg")])
def test_check_refuses_a_bad_spread(alpha0, spread, message):
    with pytest.raises(ValueError, match=message):
        opening_spread.check(alpha0, spread)
    assert not opening_spread.feasible(alpha0, spread)
    with pytest.raises(ValueError, match=message):
        simulate(drained(), {**{k: v[:1] for k, v in SETS.items()}, "alpha0": np.array([alpha0]),
                             SPREAD: np.array([spread])}, SETTINGS)


def test_the_posterior_is_cut_at_alpha0_minus_spread_45_deg():
    prior = bayes.make_prior(("alpha0", SPREAD), None, dim=3)
    assert list(prior.low) == [45.0, 0.0] and list(prior.high) == [85.0, 10.0]
    test = Measurement("t", Path("t.csv"), True, 1e5, EPS1[:2], {"q": np.array([1e4, 2e4])}, 3)
    log_post = bayes.Posterior([test], prior, SETTINGS, 0.02)
    x = np.array([[50.0, 4.0], [50.0, 6.0], [60.0, 10.0], [46.0, 0.5]])
    assert list(log_post.feasible(x)) == [True, False, True, True]
    lp = log_post(x)
    # the cut set gets -inf without a run; the others run
    assert np.isneginf(lp[1]) and log_post.n_infeasible == 1 and log_post.n_calls == 3
    with pytest.raises(ValueError, match="triaxial data"):
        bayes.make_prior(("phi_g", SPREAD), None, dim=2)


def test_the_cut_leaves_the_spread_to_the_maps_alpha0_where_the_tests_give_void_ratios():
    """With void ratios the tests run at the map's alpha0 (54.7 deg at e = 0.95 on the default map), not the fixed
    --alpha0: spreads of 8 and 9.9 deg about a fixed 50 deg are not cut; the map's alpha0 runs 8 and gives 9.9 NaN
    curves (a failed set)."""
    settings = replace(SETTINGS, fixed={**SETTINGS.fixed, "alpha0": 50.0, "e_min": 0.597, "e_max": 0.977})
    prior = bayes.make_prior(("phi_g", SPREAD), None, dim=3)
    test = Measurement("t", Path("t.csv"), True, 2e5, EPS1[:2], {"q": np.array([1e4, 2e4])}, 3, 0.95)
    values = {"phi_g": np.array([30.0, 30.0]), SPREAD: np.array([8.0, 9.9])}
    assert list(forward.feasible(values, settings)) == [False, False]  # the fixed alpha0's cut
    assert list(bayes.Posterior([test], prior, settings, 0.02).feasible(np.array([[30.0, 8.0], [30.0, 9.9]]))) == [
        True, True]
    curves = simulate(test, values, settings)
    assert np.all(np.isfinite(curves.q[0])) and np.all(np.isnan(curves.q[1]))


@pytest.fixture(scope="module")
def spread_data(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("spread")
    truth = {**{k: v[:1] for k, v in SETS.items()}, SPREAD: np.array([5.0])}
    clean = simulate(drained(folder / "tri.csv"), truth, ForwardSettings(increment=4e-3, iso_increment=2e-3))
    rows = "\n".join(f"{e:.6g},{a:.9g},{b:.9g}" for e, a, b in zip(EPS1, clean.q[0], clean.eps_v[0]))
    (folder / "tri.csv").write_text(f"# test = triaxial_drained\n# p0 = 1e5\neps1,q,eps_v\n{rows}\n")
    return folder / "tri.csv"


COMMON = ["--kn", "2e7", "--kt", "1e7", "--phi", "30", "--alpha0", "60", "--walkers", "4", "--steps", "3",
          "--increment", "4e-3", "--iso-increment", "2e-3", "-q"]

BAD = {
    "negative fixed spread": (["--params", "phi_g", "--alpha0-spread", "-1", "--confirm", "none"], "must be >= 0"),
    "fixed spread below 45": (["--params", "phi_g", "--alpha0-spread", "16", "--confirm", "none"], "below 45 deg"),
    "confirm dem": (["--params", f"phi_g,{SPREAD}"], "--confirm dem runs one opening angle"),
    "backend dem": (["--params", f"phi_g,{SPREAD}", "--backend", "dem", "--confirm", "none"], "--backend dem runs one"),
    "negative prior": (["--params", f"phi_g,{SPREAD}", "--confirm", "none", "--prior", "{prior}"], "reaches below 0"),
}


@pytest.mark.parametrize("case", BAD)
def test_calibrate_refuses_a_bad_spread_in_one_line(case, spread_data, tmp_path, capsys):
    flags, message = BAD[case]
    (tmp_path / "prior.json").write_text(json.dumps({SPREAD: [-2, 5]}))
    flags = [f.replace("{prior}", str(tmp_path / "prior.json")) for f in flags]
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(spread_data), *COMMON, *flags, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_calibrate_refuses_a_fixed_spread_that_the_datas_void_ratio_rules_out(spread_data, tmp_path, capsys):
    """A test that gives its void ratio runs at the map's alpha0 (47.07 deg at e = 0.6 on the default map): a fixed
    spread of 5 deg takes its lowest family below 45 deg there, refused before any run; 1 deg is not."""
    data = tmp_path / "dense.csv"
    data.write_text(spread_data.read_text().replace("# p0 = 1e5", "# p0 = 1e5\n# void_ratio = 0.6"))
    flags = ["--data", str(data), *[f for f in COMMON if f not in ("--alpha0", "60")], "--params", "phi_g",
             "--confirm", "none"]
    out = tmp_path / "cal"
    assert run_main(calibrate.main, [*flags, "--alpha0-spread", "5", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "void ratio 0.6" in err and "47.0655 - 5 deg is below 45 deg" in err and len(err.splitlines()) == 1
    assert not out.exists()
    args = calibrate.build_parser().parse_args([*flags, "--alpha0-spread", "1", "--out", str(out)])
    tests = calibrate.read_tests(args.data)
    settings = forward.with_density(calibrate.forward_settings(args, 3), tests, args.e_min, args.e_max)
    calibrate.check_spread_at_void_ratios(args, tests, settings)  # 46.07 deg: allowed


def test_a_spread_is_judged_at_the_void_ratios_alpha0_not_the_fixed_one(spread_data, tmp_path):
    """Where every test gives its void ratio no test runs at the fixed --alpha0: a spread of 8 deg about a fixed
    50 deg is calibrated (the tests run at the map's 54.7 deg, e = 0.95) and hmodel triaxial --posterior
    --void-ratio 0.95 replays it; both refused it at 50 - 8 = 42 deg before. --void-ratio 0.65 (47.9 deg) is
    refused at the replay's own alpha0."""
    data = tmp_path / "loose.csv"
    data.write_text(spread_data.read_text().replace("# p0 = 1e5", "# p0 = 1e5\n# void_ratio = 0.95"))
    common = [f for f in COMMON if f not in ("--alpha0", "60")]
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(data), *common, "--params", "phi_g", "--alpha0", "50",
                                     "--alpha0-spread", "8", "--e-min", "0.597", "--e-max", "0.977", "--steps", "1",
                                     "--order", "5", "--spins", "2", "--resolution", "off", "--confirm", "none",
                                     "--start", "prior",
                                     "--out", str(out)]) == 0
    run = ["triaxial", "--posterior", str(out), "--drained", "--p0", "1e5", "--eps-max", "8e-3", "--increment", "4e-3",
           "--iso-increment", "2e-3", "--order", "5", "--spins", "2", "-q"]
    assert run_main(hmodel.main, [*run, "--void-ratio", "0.95", "--out", str(tmp_path / "loose")]) == 0
    stored = io.read_run(tmp_path / "loose" / io.RUN_FILE).attrs["parameters"]
    assert stored["posterior"]["values"][SPREAD] == 8.0
    assert run_main(hmodel.main, [*run, "--void-ratio", "0.65", "--out", str(tmp_path / "dense")]) == 2
    assert not (tmp_path / "dense").exists()


def test_calibrate_refuses_a_spread_on_biaxial_data(tmp_path, capsys):
    data = tmp_path / "u.csv"
    data.write_text("# test = undrained\n# p0 = 3e6\neps1,q\n0.004,1.1e6\n0.008,1.8e6\n")
    assert run_main(calibrate.main, ["--data", str(data), "--params", f"phi_g,{SPREAD}", "--confirm", "none",
                                     "--out", str(tmp_path / "cal"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "triaxial data" in err and len(err.splitlines()) == 1


@pytest.fixture(scope="module")
def spread_posterior(spread_data) -> Path:
    out = spread_data.parent / "cal"
    assert run_main(calibrate.main, ["--data", str(spread_data), "--params", f"phi_g,{SPREAD}", *COMMON,
                                     "--resolution", "off", "--confirm", "none", "--out", str(out)]) == 0
    return out  # without the resolution correction: the band's forward_at_mean is then the command's own model


def test_calibrate_and_triaxial_posterior_run_the_spread(spread_posterior, tmp_path, capsys):
    post = json.loads((spread_posterior / "posterior.json").read_text())
    run = json.loads((spread_posterior / "run.json").read_text())
    assert set(post) == {"phi_g", SPREAD} and 0.0 <= post[SPREAD]["mean"] <= 10.0
    assert "infeasible_sets" in run["forward_model"] and "infeasible_sets" in run["start"]
    out = tmp_path / "pred"
    assert hmodel.main(["triaxial", "--posterior", str(spread_posterior), "--posterior-band", "3", "--drained",
                        "--p0", "1e5", "--eps-max", "0.02", "--increment", "4e-3", "--iso-increment", "2e-3",
                        "--order", "11", "--spins", "4", "--aligned-spins", "-q", "--out", str(out)]) == 0
    stored = io.read_run(out / io.RUN_FILE).attrs["parameters"]
    assert stored["posterior"]["values"][SPREAD] == post[SPREAD]["mean"]
    assert stored["n_orientations"] == opening_spread.N_NODES * 100  # three families of the 11 x 4 rule
    # the command's own run is the calibration's forward model at the mean (same rule and increments)
    lines = (out / "posterior_band.csv").read_text().splitlines()
    table = [line for line in lines if not line.startswith("#")]
    names = table[0].split(",")
    band = dict(zip(names, np.array([[float(v) for v in r.split(",")] for r in table[1:]]).T))
    rows = [r.split(",") for r in (out / io.CURVE_FILE).read_text().splitlines()[1:]]
    shear = np.array([[float(v) for v in r[1:]] for r in rows if r[0] == "shear"])
    start = np.array([float(v) for v in [r for r in rows if r[0] == "iso"][-1][1:]])
    q = np.interp(band["eps1"], shear[:, 0] - start[0], shear[:, 7])
    np.testing.assert_allclose(q, band["q_forward_at_mean"], rtol=0, atol=2e-4 * 1e5)
    # the DEM takes one opening angle per model: refused before any run
    capsys.readouterr()
    assert run_main(hmodel.main, ["triaxial", "--posterior", str(spread_posterior), "--backend", "dem", "--drained",
                                  "--p0", "1e5", "--eps-max", "0.02", "-q", "--out", str(tmp_path / "dem")]) == 2
    err = capsys.readouterr().err.strip()
    assert "analytical backend only" in err and len(err.splitlines()) == 1


def test_the_hertz_mindlin_law_takes_the_spread_too():
    hertz = ForwardSettings(**{**SETTINGS.__dict__, "law": "hertz-mindlin"})
    sets = {"phi_g": SETS["phi_g"], "alpha0": SETS["alpha0"], "shear_modulus": np.array([1e9, 2e9]),
            "poisson": np.array([0.2, 0.2])}
    plain = simulate(drained(), sets, hertz)
    zero = simulate(drained(), {**sets, SPREAD: np.zeros(2)}, hertz)
    np.testing.assert_allclose(zero.q, plain.q, rtol=1e-11, atol=1e-6)
    spread = simulate(drained(), {**sets, SPREAD: np.array([6.0, 5.0])}, hertz)
    assert np.max(np.abs(spread.q - plain.q)) > 1e-2 * np.max(plain.q)
