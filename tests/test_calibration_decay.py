"""The interlocking's lag over a distortion growing with pressure (``calibration.interlocking``: relax_strain,
relax_exponent): hand values of gamma_r(p), bit-unchanged without it, per set in the forward model, each increment
the hand recurrence at the point's pressure, replayed by hmodel triaxial --posterior, refused in one line where it
does not apply."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_one_line_refusal, interlocking_data
from interlocking_cases import FAST, LagRecorder, P_REF, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking, mobilised_friction_deg, relax_strain_at
from homogenization.cli import calibrate
from homogenization.material.density import current_void_ratio

EPS1 = np.linspace(0.002, 0.06, 30)
TEST = Measurement("drained", Path("drained.csv"), True, 4 * P_REF, EPS1, {"q": np.zeros(30), "eps_v": np.zeros(30)},
                   dim=3, void_ratio=0.55)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02)


def test_the_lag_strain():
    """gamma_r(p) = gamma_r (p / p_ref)^k: hand values; k = 0 is gamma_r at any p; out-of-range k refused."""
    assert relax_strain_at(4 * P_REF, 0.02, 1.0, P_REF) == pytest.approx(0.08, rel=1e-14)
    assert relax_strain_at(4 * P_REF, 0.02, 0.5, P_REF) == pytest.approx(0.04, rel=1e-14)
    np.testing.assert_array_equal(relax_strain_at(np.array([0.0, 1e5, 9e5]), 0.02, 0.0, P_REF), [0.02] * 3)
    with pytest.raises(ValueError, match="relax_exponent"):
        Interlocking(relax_exponent=-0.5).check()


def test_off_is_the_rule_bit_for_bit_and_per_set_values_count():
    """relax_strain = 0 per set is the rule without the lag bit for bit; relax_exponent = 0 per set is the
    settings' lag of the same gamma_r bit for bit; in one batch a set with k = 1 differs from the k = 0 set."""
    base = forward.simulate(TEST, SETS, SETTINGS, interlocking=RULE)
    zero = forward.simulate(TEST, {**SETS, "relax_strain": np.zeros(2), "relax_exponent": np.ones(2)}, SETTINGS,
                            interlocking=RULE)
    lag = forward.simulate(TEST, SETS, SETTINGS, interlocking=replace(RULE, relax_strain=0.02))
    flat = forward.simulate(TEST, {**SETS, "relax_strain": np.full(2, 0.02), "relax_exponent": np.zeros(2)},
                            SETTINGS, interlocking=RULE)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(zero.channel(name), base.channel(name))
        np.testing.assert_array_equal(flat.channel(name), lag.channel(name))
    mixed = forward.simulate(TEST, {**SETS, "relax_strain": np.array([0.02, 0.02]),
                                    "relax_exponent": np.array([0.0, 1.0])}, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[0], lag.q[0])
    assert np.max(np.abs(mixed.q[1] - lag.q[1])) > 0.02 * np.max(lag.q[1])


def test_each_increment_relaxes_over_the_pressure_scaled_strain():
    """Per increment and point: e_r' = e + (e_r - e) exp(-d gamma / (gamma_r (p / p_ref)^k)), e and p of the
    accepted state, d gamma = abs(d eps1 - d eps3); e_r' = e where gamma_r = 0; the friction reads e_r."""
    full = forward.full_parameters({**SETS, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    hook = LagRecorder(RULE, points.material, points.state, full["phi_g"], np.full(2, 0.55),
                     per_point={"relax_strain": np.array([0.0, 0.02]), "relax_exponent": np.array([1.0, 1.0])})
    hook.steps = []
    points.renewal = hook
    forward.simulate_points(TEST, points, SETTINGS)
    sheared = 0
    for lagged, strain, J, after, p, lagged_after in hook.steps:
        e = current_void_ratio(0.55, J)
        gamma = np.abs((after - strain)[:, 0] - (after - strain)[:, 2])
        expected = e[1] + (lagged[1] - e[1]) * np.exp(-gamma[1] / (0.02 * p[1] / P_REF))
        assert lagged_after[1] == pytest.approx(expected, rel=1e-10, abs=1e-12)
        assert lagged_after[0] == e[0]
        sheared += gamma[1] > 1e-4
    assert sheared > 10
    assert p[1] > 4 * P_REF and abs(lagged_after[1] - e[1]) > 1e-3  # a pressure factor far from 1, a lag that shows
    phi = mobilised_friction_deg(full["phi_g"], lagged_after, p, 2.0, 0.7, 0.02, 0.7, P_REF)
    np.testing.assert_allclose(hook.friction_deg, phi, rtol=1e-12)


@pytest.mark.parametrize("flags, expected", [
    (["--params", "phi_g,relax_exponent"], "add --interlocking"),
    (["--params", "phi_g,relax_exponent", "--interlocking", "--prior", "PRIOR"],
     "the prior of relax_exponent reaches 3.5"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "relax_exponent=-1"],
     "relax_exponent = -1 is out of range"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"relax_exponent": [0.0, 3.5]}))
    flags = [str(prior) if f == "PRIOR" else f for f in flags]
    out = tmp_path / "cal"
    args = ["--data", str(interlocking_data(tmp_path / "t.csv")), *flags, "--walkers", "4", "--steps", "2",
            "--out", str(out), *FAST]
    assert_one_line_refusal(capsys, calibrate.main, args, expected, out)


def test_the_posterior_holds_the_exponent_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's relax_exponent; hmodel triaxial --posterior runs it as the
    forward model does (1e-6), apart from the curve at k = 0."""
    post, data, q, model, without = calibrated_replay(
        tmp_path, "relax_exponent", "interlocking_m=4,e_gamma=0.8,xi_c=0.5,relax_strain=0.01", 1.5, prior=(1.0, 2.0))
    assert post.forward.interlocking.relax_exponent == data["relax_exponent"]["mean"] >= 1.0
    assert post.forward.interlocking.relax_strain == 0.01
    np.testing.assert_allclose(q, model, rtol=1e-6)
    assert np.max(np.abs(q - without) / without) > 3e-4  # the lag barely acts by 1.2 %: 300 x the replay's rtol
