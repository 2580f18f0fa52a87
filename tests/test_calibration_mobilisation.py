"""The interlocking friction's mobilisation (``calibration.interlocking``: mobilisation_strain, mobilisation_start):
the hyperbolic share of tan phi, bit-unchanged without it, per set in the forward model, replayed by hmodel triaxial
--posterior, refused in one line where it does not apply."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_one_line_refusal, interlocking_data
from interlocking_cases import FAST, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import (Interlocking, InterlockingFriction, mobilised_friction_deg,
                                                     mobilised_share)
from homogenization.cli import calibrate
from homogenization.material.density import current_void_ratio

EPS1 = np.linspace(0.002, 0.04, 20)
TEST = Measurement("drained", Path("drained.csv"), True, 1e5, EPS1, {"q": np.zeros(20), "eps_v": np.zeros(20)}, dim=3,
                   void_ratio=0.55)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02)


def test_the_share():
    """r = r0 + (1 - r0) g / (a + g), a = a_ref (p / p_ref)^(2/3): hand values; 1 where a_ref = 0."""
    p_ref = 101325.0
    assert mobilised_share(0.0, p_ref, 0.01, 0.4, p_ref) == pytest.approx(0.4, rel=1e-14)
    assert mobilised_share(0.01, p_ref, 0.01, 0.4, p_ref) == pytest.approx(0.7, rel=1e-14)
    # at 8 p_ref, a = 4 a_ref: g = 4 a_ref is half-way
    assert mobilised_share(0.04, 8 * p_ref, 0.01, 0.0, p_ref) == pytest.approx(0.5, rel=1e-12)
    np.testing.assert_array_equal(mobilised_share(np.array([0.0, 0.1]), 1e5, 0.0, 0.3, p_ref), [1.0, 1.0])
    g = np.linspace(0.0, 0.1, 11)
    assert np.all(np.diff(mobilised_share(g, 1e5, 0.01, 0.2, p_ref)) > 0.0)
    with pytest.raises(ValueError, match="mobilisation_start"):
        Interlocking(mobilisation_start=1.2).check()


def test_zero_strain_is_the_rule_bit_for_bit_and_a_set_mobilises_its_friction():
    """mobilisation_strain = 0 (per set) is the rule without it bit for bit; a set with a_ref > 0 is softer in the
    first percent, the other set of its batch unchanged; after the run the point's friction is the rule's times
    the share at its accumulated distortion, which is the shear's eps1 - eps3."""
    base = forward.simulate(TEST, SETS, SETTINGS, interlocking=RULE)
    zero = forward.simulate(TEST, {**SETS, "mobilisation_strain": np.zeros(2)}, SETTINGS, interlocking=RULE)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(zero.channel(name), base.channel(name))
    per_set = {**SETS, "mobilisation_strain": np.array([0.0, 0.01]), "mobilisation_start": np.array([0.3, 0.3])}
    mixed = forward.simulate(TEST, per_set, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(mixed.q[0], base.q[0])
    assert mixed.q[1, 2] < 0.95 * base.q[1, 2]
    full = forward.full_parameters({**SETS, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    hook = InterlockingFriction(replace(RULE, mobilisation_strain=0.01, mobilisation_start=0.3), points.material,
                                points.state, full["phi_g"], np.full(2, 0.55))
    points.renewal = hook
    start = {}
    forward.simulate_points(TEST, points, SETTINGS,
                            before_stage={1: lambda pts: start.update(s=pts.state.strain.copy())})
    d = points.state.strain - start["s"]
    np.testing.assert_allclose(hook.distortion, d[:, 0] - d[:, 2], rtol=1e-9, atol=1e-6)
    p = points.mean(points.state.stress)
    e = current_void_ratio(0.55, points.state.J)
    phi = mobilised_friction_deg(full["phi_g"], e, p, 2.0, 0.7, 0.02, 0.7, RULE.p_ref)
    r = mobilised_share(hook.distortion, p, 0.01, 0.3, RULE.p_ref)
    np.testing.assert_allclose(np.tan(np.radians(hook.friction_deg)), r * np.tan(np.radians(phi)), rtol=1e-12)


@pytest.mark.parametrize("flags, expected", [
    (["--params", "phi_g,mobilisation_strain"], "add --interlocking"),
    (["--params", "phi_g,mobilisation_start", "--interlocking", "--prior", "PRIOR"],
     "the prior of mobilisation_start reaches 1.5"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "mobilisation_strain=-0.01"],
     "mobilisation_strain = -0.01 is out of range"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"mobilisation_start": [0.0, 1.5]}))
    flags = [str(prior) if f == "PRIOR" else f for f in flags]
    out = tmp_path / "cal"
    args = ["--data", str(interlocking_data(tmp_path / "t.csv")), *flags, "--walkers", "4", "--steps", "2",
            "--out", str(out), *FAST]
    assert_one_line_refusal(capsys, calibrate.main, args, expected, out)


def test_the_posterior_holds_the_mobilisation_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's mobilisation_strain; hmodel triaxial --posterior runs it as the
    forward model does, apart from the curve without it."""
    post, data, q, model, without = calibrated_replay(
        tmp_path, "mobilisation_strain", "e_gamma=0.8,xi_c=0.5,mobilisation_start=0.2", 0.01)
    assert post.forward.interlocking.mobilisation_strain == data["mobilisation_strain"]["mean"] > 0.0
    assert post.forward.interlocking.mobilisation_start == 0.2
    np.testing.assert_allclose(q, model, rtol=1e-4)
    assert abs(q[0] - without[0]) > 0.05 * without[0]
