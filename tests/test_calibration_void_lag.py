"""The interlocking's lag with a void-ratio factor (``calibration.interlocking``: relax_void_slope s,
gamma_r(p, e0) = gamma_r (p / p_ref)^k exp(s (e0 - 0.55))): hand values, bit-unchanged at s = 0 (and at e0 = e_ref),
per set in the forward model, each increment the hand recurrence at the point's e0, replayed by hmodel triaxial
--posterior, refused in one line where it does not apply."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_interlocking_refusal
from interlocking_cases import FAST, LagRecorder, P_REF, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import RELAX_VOID_REF, Interlocking, relax_strain_at
from homogenization.material.density import current_void_ratio

EPS1 = np.linspace(0.002, 0.06, 30)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02, relax_strain=0.02)


def drained(void_ratio: float) -> Measurement:
    """A drained test at 2 p_ref to 6 % of the given initial void ratio (its curves are not read)."""
    return Measurement("drained", Path("drained.csv"), True, 2 * P_REF, EPS1,
                       {"q": np.zeros(30), "eps_v": np.zeros(30)}, dim=3, void_ratio=void_ratio)


def test_the_lag_strain_of_the_void_ratio():
    """gamma_r(p, e0) = gamma_r (p / p_ref)^k exp(s (e0 - 0.55)): hand values; s = 0 is the factor 1 at any e0 (NaN
    too); out-of-range s refused."""
    assert RELAX_VOID_REF == 0.55
    assert relax_strain_at(P_REF, 0.02, 0.0, P_REF, 0.65, 10.0) == pytest.approx(0.02 * math.e, rel=1e-14)
    assert relax_strain_at(4 * P_REF, 0.02, 0.5, P_REF, 0.45, 10.0) == pytest.approx(0.04 / math.e, rel=1e-14)
    np.testing.assert_array_equal(relax_strain_at(2 * P_REF, 0.02, 1.0, P_REF, np.array([0.5, np.nan]), 0.0),
                                  [0.04, 0.04])
    with pytest.raises(ValueError, match="relax_void_slope"):
        Interlocking(relax_void_slope=101.0).check()


def test_zero_slope_is_the_lag_bit_for_bit_and_the_slope_reads_the_test_void_ratio():
    """relax_void_slope = 0 per set is the lag without it bit for bit; at the test's e0 = e_ref a slope changes
    nothing (bit for bit); at e0 = 0.62 in one batch a set with s = 20 differs from the s = 0 set, and it is the
    s = 0 lag of gamma_r exp(20 (0.62 - 0.55)) bit for bit."""
    at_ref, loose = drained(0.55), drained(0.62)
    for test in (at_ref, loose):
        lag = forward.simulate(test, SETS, SETTINGS, interlocking=RULE)
        zero = forward.simulate(test, {**SETS, "relax_void_slope": np.zeros(2)}, SETTINGS, interlocking=RULE)
        for name in ("q", "p", "eps_v"):
            np.testing.assert_array_equal(zero.channel(name), lag.channel(name))
    mixed = forward.simulate(at_ref, {**SETS, "relax_void_slope": np.array([0.0, 20.0])}, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[1], mixed.q[0])
    mixed = forward.simulate(loose, {**SETS, "relax_void_slope": np.array([0.0, 20.0])}, SETTINGS, interlocking=RULE)
    lag = forward.simulate(loose, SETS, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[0], lag.q[0])
    assert np.max(np.abs(mixed.q[1] - lag.q[1])) > 0.01 * np.max(lag.q[1])
    scaled = forward.simulate(loose, {**SETS, "relax_strain": np.full(2, 0.02 * math.exp(20.0 * 0.07))}, SETTINGS,
                              interlocking=RULE)
    np.testing.assert_allclose(mixed.q[1], scaled.q[1], rtol=1e-12)


def test_each_increment_relaxes_over_the_void_ratio_scaled_strain():
    """Per increment and point: e_r' = e + (e_r - e) exp(-d gamma / (gamma_r (p / p_ref)^k exp(s (e0 - 0.55)))),
    each point its own e0 (0.5 and 0.62), e and p of the accepted state, d gamma = abs(d eps1 - d eps3)."""
    full = forward.full_parameters({**SETS, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    e0 = np.array([0.5, 0.62])
    hook = LagRecorder(RULE, points.material, points.state, full["phi_g"], e0,
                     per_point={"relax_exponent": np.array([0.5, 0.5]), "relax_void_slope": np.array([10.0, 10.0])})
    hook.steps = []
    points.renewal = hook
    forward.simulate_points(drained(0.55), points, SETTINGS)
    sheared = 0
    for lagged, strain, J, after, p, lagged_after in hook.steps:
        e = current_void_ratio(e0, J)
        gamma = np.abs((after - strain)[:, 0] - (after - strain)[:, 2])
        scale = 0.02 * (p / P_REF) ** 0.5 * np.exp(10.0 * (e0 - 0.55))
        expected = e + (lagged - e) * np.exp(-gamma / scale)
        np.testing.assert_allclose(lagged_after, expected, rtol=1e-10, atol=1e-12)
        sheared += bool(np.all(gamma > 1e-4))
    assert sheared > 10
    assert np.all(np.abs(lagged_after - e) > 1e-3)  # a lag that shows at both points (factors 0.61 and 2.0)


@pytest.mark.parametrize("flags, data, expected", [
    (["--params", "phi_g,relax_void_slope"], "given", "add --interlocking"),
    (["--params", "phi_g,relax_void_slope", "--interlocking"], "none", "gives none ('# void_ratio = E'"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "relax_strain=0.01,relax_void_slope=5"], "none",
     "relax_void_slope scales the lag by the test's void ratio"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "relax_void_slope=-150"], "given",
     "relax_void_slope = -150 is out of range"),
    (["--params", "phi_g,relax_void_slope", "--interlocking", "--prior", "PRIOR"], "given",
     "the prior of relax_void_slope reaches 120"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, data, expected):
    assert_interlocking_refusal(tmp_path, capsys, flags, data, expected, {"relax_void_slope": [0.0, 120.0]}, FAST)


def test_the_posterior_holds_the_slope_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's relax_void_slope; hmodel triaxial --posterior at void ratio 0.6
    runs it as the forward model does (1e-6), apart from the curve at s = 0."""
    post, data, q, model, without = calibrated_replay(
        tmp_path, "relax_void_slope", "interlocking_m=4,e_gamma=0.8,xi_c=0.5,relax_strain=0.01", 25, prior=(20.0, 30.0))
    assert post.forward.interlocking.relax_void_slope == data["relax_void_slope"]["mean"] >= 20.0
    np.testing.assert_allclose(q, model, rtol=1e-6)
    assert np.max(np.abs(q - without) / without) > 3e-4
    assert replace(post.forward.interlocking, relax_void_slope=0.0) != post.forward.interlocking
