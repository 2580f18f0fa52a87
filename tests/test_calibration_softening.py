"""The interlocking's softening since the peak (``calibration.interlocking``: softening_strain, with relax_exponent):
bit-unchanged without it, the rule itself until the point's densest state, each increment the hand formula at the
point's pressure after it, released to e over the strain, replayed by hmodel triaxial --posterior, refused in one
line where it does not apply."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_one_line_refusal, interlocking_data
from interlocking_cases import FAST, P_REF, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking, InterlockingFriction, mobilised_friction_deg
from homogenization.cli import calibrate
from homogenization.material.density import current_void_ratio

EPS1 = np.linspace(0.002, 0.12, 60)
TEST = Measurement("drained", Path("drained.csv"), True, 4 * P_REF, EPS1, {"q": np.zeros(60), "eps_v": np.zeros(60)},
                   dim=3, void_ratio=0.55)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02)


def test_off_is_the_rule_bit_for_bit_and_the_rise_is_not_lagged():
    """softening_strain = 0 per set is the rule bit for bit (whatever relax_exponent); with it the curve is the
    rule's bit for bit up to the densest state and differs after it, where the lag of the same strain differs from
    the first sheared increment on."""
    base = forward.simulate(TEST, SETS, SETTINGS, interlocking=RULE)
    zero = forward.simulate(TEST, {**SETS, "softening_strain": np.zeros(2), "relax_exponent": np.ones(2)}, SETTINGS,
                            interlocking=RULE)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(zero.channel(name), base.channel(name))
    soft = forward.simulate(TEST, {**SETS, "softening_strain": np.array([0.0, 0.02])}, SETTINGS, interlocking=RULE)
    lag = forward.simulate(TEST, SETS, SETTINGS, interlocking=replace(RULE, relax_strain=0.02))
    np.testing.assert_array_equal(soft.q[0], base.q[0])
    densest = int(np.argmax(base.eps_v[1]))  # eps_v > 0: contraction; the rise before it reads e itself
    assert 1 <= densest < len(EPS1) - 10
    np.testing.assert_array_equal(soft.q[1][:densest], base.q[1][:densest])
    assert np.max(np.abs(soft.q[1] - base.q[1])) > 1e-3 * np.max(base.q[1])  # 2.2e-3 here
    assert np.max(np.abs(lag.q[1][:densest] - base.q[1][:densest])) > 0.0


class _Recorder(InterlockingFriction):
    """The hook, recording each accepted increment's (strain before, J, strain and p after, e_s after)."""

    def advance(self, state):
        before = self._strain.copy()
        state = super().advance(state)
        self.steps.append((before, state.J.copy(), state.strain.copy(), self._mean(state.stress),
                           self.e_lagged.copy()))
        return state


def test_each_increment_holds_the_densest_state_and_releases_it_over_the_strain():
    """Per increment and point: e_s = e_d + (e - e_d) (1 - exp(-g_d / (gamma_s (p / p_ref)^k))) (k = 0.5), e_d the
    smallest e so far, g_d the distortion abs(d eps1 - d eps3) summed since e was last at e_d, e and p of the accepted state
    (the hand recurrence, from the states alone); e_s = e where gamma_s = 0; the friction reads e_s; after many
    gamma_s of distortion e_s is back at e (the lag's e_r trails it)."""
    full = forward.full_parameters({**SETS, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    hook = _Recorder(RULE, points.material, points.state, full["phi_g"], np.full(2, 0.55),
                     per_point={"softening_strain": np.array([0.0, 0.005]), "relax_exponent": np.array([0.5, 0.5])})
    hook.steps = []
    points.renewal = hook
    e_d, g_d = float(current_void_ratio(0.55, points.state.J)[1]), 0.0
    forward.simulate_points(TEST, points, SETTINGS)
    held, released = 0, 0
    for strain, J, after, p, e_s in hook.steps:
        e = current_void_ratio(0.55, J)
        gamma = abs((after - strain)[1, 0] - (after - strain)[1, 2])
        if e[1] <= e_d:
            e_d, g_d = e[1], 0.0
        else:
            g_d += gamma
        expected = e_d + (e[1] - e_d) * (1.0 - np.exp(-g_d / (0.005 * (p[1] / P_REF) ** 0.5)))
        assert e_s[1] == pytest.approx(expected, rel=1e-12, abs=1e-14)
        assert e_s[0] == e[0]
        held += abs(e_s[1] - e[1]) > 3e-4
        released += g_d > 0.05
    assert held > 3 and released > 5  # the hold shows, and the test runs past 0.05 of distortion after the peak
    assert p[1] > 4 * P_REF and abs(e_s[1] - e[1]) < 1e-4 < e[1] - e_d  # released: e_s is e again, above e_d
    phi = mobilised_friction_deg(full["phi_g"], e_s, p, 2.0, 0.7, 0.02, 0.7, P_REF)
    np.testing.assert_allclose(hook.friction_deg, phi, rtol=1e-12)


@pytest.mark.parametrize("flags, expected", [
    (["--params", "phi_g,softening_strain"], "add --interlocking"),
    (["--params", "phi_g,softening_strain", "--interlocking", "--prior", "PRIOR"],
     "the prior of softening_strain reaches -0.01"),
    (["--params", "phi_g,relax_strain,softening_strain", "--interlocking"], "one lag at a time"),
    (["--params", "phi_g,softening_strain", "--interlocking", "--interlocking-values", "relax_strain=0.01"],
     "the prior of softening_strain reaches 0.1: interlocking softening_strain = 0.1 with relax_strain = 0.01"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "softening_strain=0.01,relax_strain=0.01"],
     "one lag at a time"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "softening_strain=-1"],
     "softening_strain = -1 is out of range"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"softening_strain": [-0.01, 0.05]}))
    flags = [str(prior) if f == "PRIOR" else f for f in flags]
    out = tmp_path / "cal"
    args = ["--data", str(interlocking_data(tmp_path / "t.csv")), *flags, "--walkers", "4", "--steps", "2",
            "--out", str(out), *FAST]
    assert_one_line_refusal(capsys, calibrate.main, args, expected, out)


def test_the_posterior_holds_the_softening_and_triaxial_replays_it(tmp_path):
    """posterior.json's interlocking holds the mean's softening_strain; hmodel triaxial --posterior runs it as the
    forward model does (1e-6), apart from the curve without it."""
    post, data, q, model, without = calibrated_replay(
        tmp_path, "softening_strain", "interlocking_m=4,e_gamma=0.8,xi_c=0.5,relax_exponent=1", 0.01,
        prior=(0.005, 0.02))
    assert post.forward.interlocking.softening_strain == data["softening_strain"]["mean"] >= 0.005
    assert post.forward.interlocking.relax_exponent == 1.0
    np.testing.assert_allclose(q, model, rtol=1e-6)
    assert np.max(np.abs(q - without) / without) > 1e-3
