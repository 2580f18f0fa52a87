"""The interlocking's stiffness by density (``stiffness_void_slope`` s_k: each test's kn times exp(-s_k (e0 - 0.55)),
``interlocking.stiffness_factor``, read by ``forward.simulate``): hand values, s_k = 0 bit for bit, per set in the
forward model as a softer kn of the same set, e0 from the test's void ratio or the map's, replayed by hmodel triaxial
--posterior, refused in one line where it cannot act."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_interlocking_refusal
from interlocking_cases import FAST, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking, stiffness_factor

EPS1 = np.linspace(0.002, 0.04, 20)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.04, xi=0.5)


def drained(void_ratio: float | None) -> Measurement:
    """A drained test at 200 kPa to 4 % of the given initial void ratio (its curves are not read)."""
    return Measurement("drained", Path("drained.csv"), True, 2e5, EPS1, {"q": np.zeros(20), "eps_v": np.zeros(20)},
                       dim=3, void_ratio=void_ratio)


def test_the_factor_by_hand_and_its_range():
    """exp(-s (e0 - 0.55)): exp(-0.5) at e0 0.6, s 10; exp(0.5) at e0 0.5; 1 at e0 0.55 and, exactly, at s = 0 (NaN e0
    included); the default is 0; |s| > 100 refused by the rule."""
    assert Interlocking().stiffness_void_slope == 0.0
    assert stiffness_factor(0.6, 10.0) == pytest.approx(math.exp(-0.5), rel=1e-15)
    assert stiffness_factor(0.5, 10.0) == pytest.approx(math.exp(0.5), rel=1e-15)
    assert stiffness_factor(0.55, 7.0) == 1.0
    assert stiffness_factor(np.nan, 0.0) == 1.0 and stiffness_factor(0.7, 0.0) == 1.0
    replace(RULE, stiffness_void_slope=-100.0).check()
    for value in (-101.0, 101.0, np.nan):
        with pytest.raises(ValueError, match="stiffness_void_slope"):
            replace(RULE, stiffness_void_slope=value).check()


def test_zero_slope_is_bit_for_bit_and_a_slope_is_the_same_set_at_a_softer_kn():
    """s_k = 0 per set is the run without it bit for bit; a set at s_k = 10 on a test of void ratio 0.6 is the set
    without it at kn exp(-0.5) (1e-12), and differs from it by more than 5 % of q; with the interlocking's own s_k and
    a test without a void ratio, e0 is the map's of alpha0 (55 deg on [0.45, 0.7]: 0.69096); a slope out of range per
    set is refused."""
    settings = replace(SETTINGS, interlocking=RULE)
    test = drained(0.6)
    plain = forward.simulate(test, SETS, settings)
    zero = forward.simulate(test, {**SETS, "stiffness_void_slope": np.zeros(2)}, settings)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(zero.channel(name), plain.channel(name))
    sloped = forward.simulate(test, {**SETS, "stiffness_void_slope": np.array([0.0, 10.0])}, settings)
    np.testing.assert_array_equal(sloped.q[0], plain.q[0])
    softer = forward.simulate(test, {**SETS, "kn": SETS["kn"] * math.exp(-0.5)}, settings)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_allclose(sloped.channel(name)[1], softer.channel(name)[1], rtol=1e-12, atol=1e-15)
    assert np.max(np.abs(sloped.q[1] - plain.q[1])) > 0.05 * np.max(plain.q[1])
    unmapped = replace(test, void_ratio=None)
    alpha = {**SETS, "alpha0": np.full(2, 55.0)}
    e0 = 0.7 - (55.3 - 55.0) / (55.3 - 47.0) * (0.7 - 0.45)
    assert e0 == pytest.approx(0.69096, abs=1e-5)
    own = forward.simulate(unmapped, alpha, replace(settings, interlocking=replace(RULE, stiffness_void_slope=10.0)))
    by_hand = forward.simulate(unmapped, {**alpha, "kn": SETS["kn"] * math.exp(-10.0 * (e0 - 0.55))}, settings)
    np.testing.assert_allclose(own.q, by_hand.q, rtol=1e-12)
    with pytest.raises(ValueError, match="stiffness_void_slope = 120 is out of range"):
        forward.simulate(test, {**SETS, "stiffness_void_slope": np.array([0.0, 120.0])}, settings)


def test_the_hertz_mindlin_law_has_no_kn_to_scale():
    with pytest.raises(ValueError, match="stiffness_void_slope scales the linear law's kn"):
        forward.simulate(drained(0.6), {"phi_g": np.array([30.0]), "e_min": np.array([0.45]),
                                        "e_max": np.array([0.7])},
                         replace(SETTINGS, law="hertz-mindlin", interlocking=replace(RULE, stiffness_void_slope=5.0)))


@pytest.mark.parametrize("flags, expected", [
    (["--params", "phi_g,stiffness_void_slope"], "--params stiffness_void_slope: the interlocking friction's; add "
                                                 "--interlocking"),
    (["--params", "phi_g,shear_modulus,stiffness_void_slope", "--interlocking", "--law", "hertz-mindlin"],
     "--params stiffness_void_slope is not a parameter of the hertz-mindlin contact law"),
    (["--params", "phi_g,shear_modulus", "--interlocking", "--law", "hertz-mindlin", "--interlocking-values",
      "stiffness_void_slope=5"], "stiffness_void_slope scales the linear law's kn"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "stiffness_void_slope=150"],
     "stiffness_void_slope = 150 is out of range"),
    (["--params", "phi_g,stiffness_void_slope", "--interlocking", "--prior", "PRIOR"],
     "the prior of stiffness_void_slope reaches 120"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    assert_interlocking_refusal(tmp_path, capsys, flags, "given", expected, {"stiffness_void_slope": [0.0, 120.0]},
                                FAST)


def test_the_posterior_holds_the_slope_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's stiffness_void_slope; hmodel triaxial --posterior at void ratio
    0.6 and 200 kPa runs it as the forward model does (1e-4), apart from the curve at s_k = 0 by more than 2 %."""
    post, data, q, model, without = calibrated_replay(tmp_path, "stiffness_void_slope",
                                                      "e_gamma=0.9,lambda_c=0.1,xi_c=0.5", 10.0, prior=(8.0, 12.0))
    assert post.forward.interlocking.stiffness_void_slope == data["stiffness_void_slope"]["mean"] >= 8.0
    np.testing.assert_allclose(q, model, rtol=1e-4)
    assert np.max(np.abs(q - without) / without) > 0.02
