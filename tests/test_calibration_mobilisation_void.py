"""The interlocking's mobilisation strain with a void-ratio factor and a free pressure exponent
(``calibration.interlocking``: mobilisation_void_slope s_m, mobilisation_exponent n, a(p, e0) = a_ref (p / p_ref)^n
exp(s_m (e0 - 0.55))): hand values, bit-unchanged at the defaults (and at e0 = e_ref), per set in the forward model,
each point's friction the hand share at its own e0 and n, replayed by hmodel triaxial --posterior, refused in one line
where it does not apply."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_interlocking_refusal
from interlocking_cases import FAST, P_REF, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import (MOBILISATION_EXPONENT, Interlocking, InterlockingFriction,
                                                     mobilised_friction_deg, mobilised_share)
from homogenization.material.density import current_void_ratio

EPS1 = np.linspace(0.002, 0.04, 20)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02, mobilisation_strain=0.01, mobilisation_start=0.3)


def drained(void_ratio: float) -> Measurement:
    """A drained test at p_ref to 4 % of the given initial void ratio (its curves are not read)."""
    return Measurement("drained", Path("drained.csv"), True, P_REF, EPS1,
                       {"q": np.zeros(20), "eps_v": np.zeros(20)}, dim=3, void_ratio=void_ratio)


def test_the_share_of_the_void_ratio_and_exponent():
    """a = a_ref (p / p_ref)^n exp(s_m (e0 - 0.55)); g = a is half-way from r0 to 1: hand values; s_m = 0 is the
    factor 1 at any e0 (NaN too); out-of-range values refused."""
    assert Interlocking().mobilisation_exponent == MOBILISATION_EXPONENT == 2.0 / 3.0
    a = 0.01 * math.e
    assert mobilised_share(a, P_REF, 0.01, 0.0, P_REF, 0.65, 10.0) == pytest.approx(0.5, rel=1e-14)
    # n = 0: no pressure factor at 8 p_ref; n = 1: a factor 8
    assert mobilised_share(0.01 / math.e, 8 * P_REF, 0.01, 0.0, P_REF, 0.45, 10.0, 0.0) == pytest.approx(0.5, rel=1e-14)
    assert mobilised_share(0.08, 8 * P_REF, 0.01, 0.4, P_REF, 0.55, 10.0, 1.0) == pytest.approx(0.7, rel=1e-14)
    np.testing.assert_array_equal(mobilised_share(0.04, 8 * P_REF, 0.01, 0.0, P_REF, np.array([0.5, np.nan]), 0.0),
                                  np.full(2, mobilised_share(0.04, 8 * P_REF, 0.01, 0.0, P_REF)))
    for field, value in (("mobilisation_void_slope", 101.0), ("mobilisation_exponent", -0.1),
                         ("mobilisation_exponent", 3.5)):
        with pytest.raises(ValueError, match=field):
            replace(Interlocking(), **{field: value}).check()


def test_defaults_are_the_mobilisation_bit_for_bit_and_the_slope_reads_the_test_void_ratio():
    """mobilisation_void_slope = 0 and mobilisation_exponent = 2/3 per set are the mobilisation without them bit for
    bit; at the test's e0 = e_ref a slope changes nothing; at e0 = 0.62 in one batch a set with s_m = 20 differs from
    the s_m = 0 set, and it is the s_m = 0 mobilisation of a_ref exp(20 (0.62 - 0.55)) (1e-10)."""
    at_ref, loose = drained(0.55), drained(0.62)
    for test in (at_ref, loose):
        plain = forward.simulate(test, SETS, SETTINGS, interlocking=RULE)
        zero = forward.simulate(test, {**SETS, "mobilisation_void_slope": np.zeros(2),
                                       "mobilisation_exponent": np.full(2, 2.0 / 3.0)}, SETTINGS, interlocking=RULE)
        for name in ("q", "p", "eps_v"):
            np.testing.assert_array_equal(zero.channel(name), plain.channel(name))
    slope = {**SETS, "mobilisation_void_slope": np.array([0.0, 20.0])}
    mixed = forward.simulate(at_ref, slope, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[1], mixed.q[0])
    mixed = forward.simulate(loose, slope, SETTINGS, interlocking=RULE)
    plain = forward.simulate(loose, SETS, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[0], plain.q[0])
    assert np.max(np.abs(mixed.q[1] - plain.q[1])) > 0.05 * np.max(plain.q[1])
    scaled = forward.simulate(loose, {**SETS, "mobilisation_strain": np.full(2, 0.01 * math.exp(20.0 * 0.07))},
                              SETTINGS, interlocking=RULE)
    np.testing.assert_allclose(mixed.q[1], scaled.q[1], rtol=1e-10)


def test_each_point_mobilises_over_its_own_void_ratio_and_exponent():
    """After a drained run, each point's tan phi is the rule's times r at (g, a_ref (p / p_ref)^n exp(s_m (e0 -
    0.55))), its own e0 (0.5, 0.62) and n (0, 1), g = eps1 - eps3 of the shear; the two shares differ."""
    full = forward.full_parameters({**SETS, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    e0 = np.array([0.5, 0.62])
    n = np.array([0.0, 1.0])
    hook = InterlockingFriction(RULE, points.material, points.state, full["phi_g"], e0,
                                per_point={"mobilisation_void_slope": np.array([10.0, 10.0]), "mobilisation_exponent": n})
    points.renewal = hook
    forward.simulate_points(replace(drained(0.55), p0=2 * P_REF), points, SETTINGS)
    p = points.mean(points.state.stress)
    e = current_void_ratio(e0, points.state.J)
    phi = mobilised_friction_deg(full["phi_g"], e, p, 2.0, 0.7, 0.02, 0.7, P_REF)
    a = 0.01 * (p / P_REF) ** n * np.exp(10.0 * (e0 - 0.55))
    r = 0.3 + 0.7 * hook.distortion / (a + hook.distortion)
    np.testing.assert_allclose(np.tan(np.radians(hook.friction_deg)), r * np.tan(np.radians(phi)), rtol=1e-12)
    assert np.all(hook.distortion > 0.03) and abs(r[1] - r[0]) > 0.05


@pytest.mark.parametrize("flags, data, expected", [
    (["--params", "phi_g,mobilisation_void_slope"], "given", "add --interlocking"),
    (["--params", "phi_g,mobilisation_strain,mobilisation_void_slope", "--interlocking"], "none",
     "mobilisation_void_slope scales the mobilisation strain by the test's void ratio: --data"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values",
      "mobilisation_strain=0.01,mobilisation_void_slope=5"], "none", "gives none ('# void_ratio = E'"),
    (["--params", "phi_g,mobilisation_void_slope", "--interlocking"], "given",
     "mobilisation_void_slope shapes the mobilisation strain: calibrate mobilisation_strain or give it"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "mobilisation_exponent=0"], "given",
     "mobilisation_exponent shapes the mobilisation strain"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "mobilisation_void_slope=-150"], "given",
     "mobilisation_void_slope = -150 is out of range"),
    (["--params", "phi_g,mobilisation_exponent", "--interlocking", "--interlocking-values", "mobilisation_strain=0.01",
      "--prior", "PRIOR"], "given",
     "the prior of mobilisation_exponent reaches 4"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, data, expected):
    assert_interlocking_refusal(tmp_path, capsys, flags, data, expected, {"mobilisation_exponent": [0.0, 4.0]}, FAST)


def test_the_posterior_holds_the_slope_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's mobilisation_void_slope and the given exponent; hmodel triaxial
    --posterior at void ratio 0.6 runs them as the forward model does (1e-4), apart from the curve at s_m = 0."""
    post, data, q, model, without = calibrated_replay(
        tmp_path, "mobilisation_void_slope",
        "e_gamma=0.8,xi_c=0.5,mobilisation_strain=0.01,mobilisation_start=0.2,mobilisation_exponent=0", 25,
        prior=(20.0, 30.0))
    assert post.forward.interlocking.mobilisation_void_slope == data["mobilisation_void_slope"]["mean"] >= 20.0
    assert post.forward.interlocking.mobilisation_exponent == 0.0
    np.testing.assert_allclose(q, model, rtol=1e-4)
    assert np.max(np.abs(q - without) / without) > 0.05
