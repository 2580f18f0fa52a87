"""hmodel calibrate --kn-exponent N (or --params kn_exponent, N per set): each triaxial test runs the linear law's kn
(p0 / 101.325 kPa)^N, in the likelihood, in posterior.json's replay by hmodel triaxial --posterior, and nowhere
without the flag."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_one_line_refusal

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.cli import calibrate, posterior_flags, triaxial
from warp_hcell.core.cli import run_main

EPS1 = np.array([0.004, 0.008, 0.012])
SETTINGS = forward.ForwardSettings(lebedev_order=7, n_spins=2, increment=4e-3, iso_increment=2e-3)
P0 = 2e5
TEST = Measurement("t", Path("t.csv"), True, P0, EPS1, {"q": np.zeros(3)}, 3)
KN = 3e7
FAST = ["--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none", "--resolution", "off", "-q"]


def _write(path: Path, test: str = "triaxial_drained", p0: float = P0) -> Path:
    path.write_text(f"# test = {test}\n# p0 = {p0:g}\neps1,q\n0.004,250000\n0.008,380000\n0.012,430000\n")
    return path


def test_each_test_runs_kn_at_its_confining_pressure():
    """A set's curve with exponent n is the curve without it at kn (p0 / p_ref)^n, bit for bit; also for the
    sets of a test whose void ratio one set's map misses (the reached ones run once more, scaled once)."""
    n = 0.5
    scaled = KN * (P0 / SETTINGS.kn_p_ref) ** n
    with_n = forward.simulate(TEST, {"kn": np.array([KN])}, replace(SETTINGS, kn_exponent=n))
    by_hand = forward.simulate(TEST, {"kn": np.array([scaled])}, SETTINGS)
    plain = forward.simulate(TEST, {"kn": np.array([KN])}, SETTINGS)
    np.testing.assert_array_equal(with_n.q, by_hand.q)
    assert abs(with_n.q[0, 0] - plain.q[0, 0]) > 0.05 * abs(plain.q[0, 0])
    at_ref = replace(TEST, p0=SETTINGS.kn_p_ref)
    np.testing.assert_array_equal(forward.simulate(at_ref, {"kn": np.array([KN])}, replace(SETTINGS, kn_exponent=n)).q,
                                  forward.simulate(at_ref, {"kn": np.array([KN])}, SETTINGS).q)
    dense = replace(TEST, void_ratio=0.6)
    both = forward.simulate(dense, {"kn": np.array([KN, KN]), "e_min": np.array([0.45, 0.3]),
                                    "e_max": np.array([0.75, 0.5])}, replace(SETTINGS, kn_exponent=n))
    one = forward.simulate(dense, {"kn": np.array([scaled]), "e_min": np.array([0.45]), "e_max": np.array([0.75])},
                           SETTINGS)
    np.testing.assert_array_equal(both.q[0], one.q[0])
    assert np.isnan(both.q[1]).all()


def test_a_biaxial_test_or_another_law_is_refused():
    flat = Measurement("b", Path("b.csv"), False, 2e5, EPS1, {"q": np.zeros(3)}, 2)
    with pytest.raises(ValueError, match="biaxial"):
        forward.simulate(flat, {"kn": np.array([KN])}, replace(SETTINGS, kn_exponent=0.5, n_orientations=4))
    with pytest.raises(ValueError, match="law hertz-mindlin"):
        forward.simulate(TEST, {"phi_g": np.array([30.0])}, replace(SETTINGS, law="hertz-mindlin", kn_exponent=0.5))


def test_without_the_exponent_the_records_read_as_before():
    """run.json's and chain.h5's forward settings name the exponent only where it is set (old chains resume)."""
    assert not {"kn_exponent", "kn_p_ref"} & set(forward.settings_record(SETTINGS))
    assert forward.settings_record(replace(SETTINGS, kn_exponent=0.5))["kn_exponent"] == 0.5


@pytest.mark.parametrize("flags, data, expected", [
    (["--kn-exponent", "1.5"], "triaxial_drained", "must be in [0, 1]"),
    (["--kn-exponent", "x"], "triaxial_drained", "is not a number"),
    (["--kn-exponent", "0.5"], "drained", "needs triaxial data"),
    (["--kn-exponent", "0.5", "--law", "hertz-mindlin"], "triaxial_drained", "has its own pressure dependence"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, data, expected):
    path = _write(tmp_path / "t.csv", data)
    params = "phi_g,shear_modulus" if "hertz-mindlin" in flags else "phi_g,kn"
    out = tmp_path / "cal"
    assert_one_line_refusal(capsys, calibrate.main, ["--data", str(path), "--params", params, *flags, "--walkers", "4",
                                                     "--steps", "2", *FAST, "--out", str(out)], expected, out)


def test_the_posterior_replays_kn_at_the_commands_pressure(tmp_path):
    """A calibration with --kn-exponent records it; hmodel triaxial --posterior at another p0 runs the posterior
    mean's kn (its value at p_ref) times (p0 / p_ref)^n, and kt with it."""
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(_write(tmp_path / "t.csv")), "--params", "phi_g,kn",
                                     "--kn-exponent", "0.5", "--walkers", "4", "--steps", "2", "--start", "prior",
                                     *FAST, "--out", str(out)]) == 0
    from homogenization.calibration import posterior as post_mod  # noqa: PLC0415

    post = post_mod.read_posterior(out)
    assert post.forward.kn_exponent == 0.5 and post.forward.kn_p_ref == SETTINGS.kn_p_ref
    argv = ["--posterior", str(out), "--drained", "--p0", "4e5", "--eps-max", "0.01", "--out", str(tmp_path / "run")]
    args = triaxial.build_parser().parse_args(argv)
    run = posterior_flags.apply_posterior(args, argv, triaxial.build_parser(), dim=3)
    factor = (4e5 / SETTINGS.kn_p_ref) ** 0.5
    assert args.kn == pytest.approx(post.contact_law.kn * factor, rel=1e-12)
    assert args.kt == pytest.approx(post.contact_law.kt * factor, rel=1e-12)
    assert run.kn_scale == pytest.approx(factor, rel=1e-12)


def test_a_calibrated_exponent_scales_each_sets_kn_by_its_own():
    """--params kn_exponent: set i runs kn (p0 / p_ref)^n_i, in place of the settings' exponent; also for the sets
    of a test whose void ratio one set's map misses."""
    n = np.array([0.5, 0.0])
    settings = replace(SETTINGS, kn_exponent=0.3)  # overridden by the calibrated value
    both = forward.simulate(TEST, {"kn": np.array([KN, KN]), "kn_exponent": n}, settings)
    scaled = forward.simulate(TEST, {"kn": np.array([KN * (P0 / SETTINGS.kn_p_ref) ** 0.5])}, SETTINGS)
    plain = forward.simulate(TEST, {"kn": np.array([KN])}, SETTINGS)
    np.testing.assert_allclose(both.q[0], scaled.q[0], rtol=1e-9)
    np.testing.assert_allclose(both.q[1], plain.q[0], rtol=1e-9)
    assert abs(both.q[0, 0] - both.q[1, 0]) > 0.05 * abs(both.q[1, 0])
    dense = replace(TEST, void_ratio=0.6)
    mapped = forward.simulate(dense, {"kn": np.array([KN, KN]), "e_min": np.array([0.45, 0.3]),
                                      "e_max": np.array([0.75, 0.5]), "kn_exponent": np.array([0.5, 0.5])}, SETTINGS)
    one = forward.simulate(dense, {"kn": np.array([KN]), "e_min": np.array([0.45]), "e_max": np.array([0.75])},
                           replace(SETTINGS, kn_exponent=0.5))
    np.testing.assert_allclose(mapped.q[0], one.q[0], rtol=1e-9)
    assert np.isnan(mapped.q[1]).all()


@pytest.mark.parametrize("flags, data, params, expected", [
    (["--kn-exponent", "0.5"], "triaxial_drained", "phi_g,kn,kn_exponent", "the exponent is calibrated"),
    ([], "drained", "phi_g,kn,kn_exponent", "needs triaxial data"),
    (["--law", "hertz-mindlin"], "triaxial_drained", "phi_g,shear_modulus,kn_exponent",
     "is not a parameter of the hertz-mindlin contact law"),
    (["--backend", "ann"], "triaxial_drained", "phi_g,kn,kn_exponent", "the ANN is trained at one kn"),
])
def test_a_calibrated_exponent_where_it_has_no_meaning_exits_2(tmp_path, capsys, flags, data, params, expected):
    path = _write(tmp_path / "t.csv", data)
    out = tmp_path / "cal"
    assert_one_line_refusal(capsys, calibrate.main, ["--data", str(path), "--params", params, *flags, "--walkers", "6",
                                                     "--steps", "2", *FAST, "--out", str(out)], expected, out)


def test_the_posterior_replays_the_calibrated_exponent(tmp_path):
    """A calibration of kn_exponent: posterior.json holds its mean, and hmodel triaxial --posterior at another p0
    runs the mean's kn times (p0 / p_ref)^(the mean's exponent)."""
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(_write(tmp_path / "t.csv")), "--params", "phi_g,kn,kn_exponent",
                                     "--walkers", "6", "--steps", "2", "--start", "prior", *FAST, "--out", str(out)]) == 0
    from homogenization.calibration import posterior as post_mod  # noqa: PLC0415

    post = post_mod.read_posterior(out)
    n = post.mean["kn_exponent"]
    assert 0.0 < n < 1.0 and post.forward.kn_exponent == n
    argv = ["--posterior", str(out), "--drained", "--p0", "4e5", "--eps-max", "0.01", "--out", str(tmp_path / "run")]
    args = triaxial.build_parser().parse_args(argv)
    run = posterior_flags.apply_posterior(args, argv, triaxial.build_parser(), dim=3)
    factor = (4e5 / SETTINGS.kn_p_ref) ** n
    assert args.kn == pytest.approx(post.contact_law.kn * factor, rel=1e-12)
    assert run.kn_scale == pytest.approx(factor, rel=1e-12)
