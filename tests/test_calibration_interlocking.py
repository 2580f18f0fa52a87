"""The interlocking friction of the calibration's forward model (``calibration.interlocking``, opt-in)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import (Interlocking, InterlockingFriction, critical_void_ratio, spread_factors,
                                                     mobilised_friction_deg)
from homogenization.material.critical_state import DEFAULTS
from homogenization.material.density import current_void_ratio

SETTINGS = forward.ForwardSettings(increment=2e-3, iso_increment=1e-3, lebedev_order=5, n_spins=2, stress_rtol=1e-5)
EPS1 = np.linspace(0.002, 0.06, 30)
TEST = Measurement("drained", Path("drained.csv"), True, 1e5, EPS1, {"q": np.zeros(30), "eps_v": np.zeros(30)}, dim=3)
SETS = {"phi_g": np.array([30.0, 34.0]), "kn": np.array([2e7, 5e7]), "kt_over_kn": np.array([0.8, 1.2]),
        "alpha0": np.array([48.0, 50.0])}


def test_the_friction_law():
    rule = Interlocking(m=2.0, e_gamma=0.8, lambda_c=0.1, xi=0.7)
    p = np.array([0.0, 5e4, 2e5])
    e_c = critical_void_ratio(p, rule.e_gamma, rule.lambda_c, rule.xi, rule.p_ref)
    np.testing.assert_allclose(e_c, 0.8 - 0.1 * (p / 101325.0) ** 0.7, rtol=1e-14)
    # at e = e_c the friction is phi_mu, whatever m and p
    np.testing.assert_allclose(mobilised_friction_deg(32.0, e_c, p, 2.0, 0.8, 0.1, 0.7, rule.p_ref), 32.0, rtol=1e-12)
    # a hand value: e_c / e = 1.2, m = 2
    hand = np.degrees(np.arctan(1.44 * np.tan(np.radians(30.0))))
    assert mobilised_friction_deg(30.0, 0.5, 0.0, 2.0, 0.6, 0.0, 0.7, rule.p_ref) == pytest.approx(hand, rel=1e-12)
    # falls with the void ratio, and at one void ratio with the pressure; m = 0: phi_mu
    e = np.linspace(0.4, 0.9, 11)
    assert np.all(np.diff(mobilised_friction_deg(30.0, e, 1e5, 1.5, 0.8, 0.1, 0.7, rule.p_ref)) < 0.0)
    assert np.all(np.diff(mobilised_friction_deg(30.0, 0.6, p, 1.5, 0.8, 0.1, 0.7, rule.p_ref)) < 0.0)
    assert np.all(mobilised_friction_deg(30.0, e, 1e5, 0.0, 0.8, 0.1, 0.7, rule.p_ref) == pytest.approx(30.0, abs=1e-12))
    with pytest.raises(ValueError, match="lambda_c"):
        Interlocking(lambda_c=-0.1).check()


@pytest.mark.parametrize("rule", [None, DEFAULTS[3]])
def test_m_zero_is_the_plain_contact_law_bit_for_bit(rule):
    settings = replace(SETTINGS, critical_state=rule)
    sets = {**SETS, "alpha0": np.array([48.0, 57.0])}  # the loose one renews (in the increments' trials)
    plain = forward.simulate(TEST, sets, settings)
    flat = forward.simulate(TEST, sets, settings, interlocking=Interlocking(m=0.0))
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(flat.channel(name), plain.channel(name))


def test_each_point_runs_at_its_own_state_and_dense_points_gain_strength():
    """Per point, the friction after the run is the law's at the point's own e and p; the denser set at low
    pressure gets friction above phi_mu, falling as it dilates; its peak q rises."""
    rule = Interlocking(xi=0.7)
    per_set = {"m": np.array([1.5, 3.0]), "e_gamma": np.array([0.75, 0.70]), "lambda_c": np.array([0.05, 0.02])}
    e0 = np.array([0.55, 0.60])
    full = forward.full_parameters(SETS, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    hook = InterlockingFriction(rule, points.material, points.state, full["phi_g"], e0, per_set)
    start = hook.friction_deg.copy()
    points.renewal = hook
    seen = []
    curves = forward.simulate_points(TEST, points, SETTINGS,
                                     before_stage={1: lambda pts: seen.append(hook.friction_deg.copy())})
    e = current_void_ratio(e0, points.state.J)
    p = points.mean(points.state.stress)
    expected = mobilised_friction_deg(full["phi_g"], e, p, per_set["m"], per_set["e_gamma"], per_set["lambda_c"],
                                      rule.xi, rule.p_ref)
    np.testing.assert_allclose(hook.friction_deg, expected, rtol=1e-12)
    np.testing.assert_allclose(hook.owner.mu, np.repeat(np.tan(np.radians(expected)), points.material.orient.n_cells),
                               rtol=1e-12)
    assert np.all(start > full["phi_g"] + 3.0)  # e0 well below e_Gamma
    assert np.all(hook.friction_deg < seen[0])  # dilated in shear: e nearer e_c
    assert hook.floored.sum() == 0 and hook.fallbacks.sum() == 0
    plain = forward.simulate(TEST, SETS, SETTINGS)
    assert np.all(curves.q.max(axis=1) > 1.1 * plain.q.max(axis=1))


def test_a_test_with_its_void_ratio_runs_each_set_from_it():
    """e0 is the test's void ratio; a set whose map misses it gets NaN, the others run as alone."""
    test = replace(TEST, void_ratio=0.6)
    rule = Interlocking(m=2.0, e_gamma=0.75, lambda_c=0.05)
    sets = {**{k: np.append(v, v[0]) for k, v in SETS.items() if k != "alpha0"},
            "e_min": np.array([0.45, 0.5, 0.65]), "e_max": np.array([0.8, 0.9, 0.9])}
    both = forward.simulate(test, sets, SETTINGS, interlocking=rule)
    assert np.all(np.isnan(both.q[2])) and np.all(np.isfinite(both.q[:2]))
    one = forward.simulate(test, {k: v[1:2] for k, v in sets.items()}, SETTINGS, interlocking=rule)
    np.testing.assert_allclose(both.q[1], one.q[0], rtol=1e-12)
    low = forward.simulate(test, {k: v[1:2] for k, v in sets.items()}, SETTINGS,
                           interlocking=replace(rule, e_gamma=0.65))  # e0 nearer e_c: less strength
    assert low.q[0].max() < one.q[0].max()


def test_the_cells_spread_of_friction():
    """cell_spread s: a point's cells step with tan phi (1 + s u_k), u_k the n uniform quantiles of [-1, 1] dealt
    over the cells; the point's mean is the rule's tan phi; s = 0 leaves every cell at tan phi; per point."""
    n_cells = 40
    u = np.sort(spread_factors(n_cells, 0.3) - 1.0) / 0.3
    np.testing.assert_allclose(u, (2.0 * np.arange(n_cells) + 1.0) / n_cells - 1.0, atol=1e-12)
    first = spread_factors(n_cells, 0.3)[:8]
    assert np.ptp(first) > 0.3  # neighbours in the cell order (one orientation's spins) are spread apart
    full = forward.full_parameters(SETS, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    per_set = {"m": np.array([1.5, 1.5]), "e_gamma": np.array([0.75, 0.75]), "lambda_c": np.array([0.05, 0.05]),
               "cell_spread": np.array([0.0, 0.3])}
    hook = InterlockingFriction(Interlocking(), points.material, points.state, full["phi_g"], np.array([0.55, 0.55]),
                                per_set)
    mu = hook.owner.mu.reshape(2, -1)
    tan = np.tan(np.radians(hook.friction_deg))
    assert np.all(mu[0] == tan[0])
    np.testing.assert_allclose(mu[1].mean(), tan[1], rtol=1e-12)
    n = mu.shape[1]
    np.testing.assert_allclose([mu[1].min(), mu[1].max()], tan[1] * (1.0 + 0.3 * np.array([1.0 / n - 1.0, 1.0 - 1.0 / n])),
                               rtol=1e-12)
    with pytest.raises(ValueError, match="cell_spread"):
        Interlocking(cell_spread=1.0).check()


def test_the_spread_reaches_the_forward_model_and_softens_the_peak():
    """forward.simulate reads cell_spread per set: s = 0 is the unspread run bit for bit, s = 0.4 another curve
    whose cells slide one after the other, so its peak is lower."""
    test = replace(TEST, void_ratio=0.55)
    rule = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02)
    sets = {**{k: v for k, v in SETS.items() if k != "alpha0"}, "e_min": np.array([0.45, 0.45]),
            "e_max": np.array([0.7, 0.7])}
    base = forward.simulate(test, sets, SETTINGS, interlocking=rule)
    zero = forward.simulate(test, {**sets, "cell_spread": np.zeros(2)}, SETTINGS, interlocking=rule)
    np.testing.assert_array_equal(zero.q, base.q)
    spread = forward.simulate(test, {**sets, "cell_spread": np.array([0.0, 0.4])}, SETTINGS, interlocking=rule)
    np.testing.assert_array_equal(spread.q[0], base.q[0])
    assert spread.q[1].max() < base.q[1].max()


def test_the_lagged_void_ratio_follows_the_distortion():
    """relax_strain gamma_r: the friction reads a void ratio that lags the point's in shear (for the dilating set,
    between the start's and the current one); a tiny gamma_r is the unlagged rule within 1 % (the lag
    holds e0 through the isotropic stage, which has no distortion)."""
    test = replace(TEST, void_ratio=0.55)
    rule = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.02)
    sets = {**{k: v for k, v in SETS.items() if k != "alpha0"}, "e_min": np.array([0.45, 0.45]),
            "e_max": np.array([0.7, 0.7])}
    full = forward.full_parameters({**sets, "alpha0": np.array([50.0, 50.0])}, SETTINGS)
    runs = {}
    for gamma_r in (0.0, 1e-9, 0.05):
        points = forward.population(full, SETTINGS, 3)
        hook = InterlockingFriction(replace(rule, relax_strain=gamma_r), points.material, points.state, full["phi_g"],
                                    np.full(2, 0.55))
        points.renewal = hook
        start = {}
        runs[gamma_r] = (forward.simulate_points(test, points, SETTINGS, before_stage={
            1: lambda pts, s=start, h=hook: s.update(e=h.e_lagged.copy())}), hook, points, start)
    curves0, _, _, _ = runs[0.0]
    np.testing.assert_allclose(runs[1e-9][0].q, curves0.q, rtol=1e-2)
    assert np.max(np.abs(runs[0.05][0].q - curves0.q) / curves0.q.max()) > 0.03  # the lag changes the curve
    _, hook, points, start = runs[0.05]
    e = current_void_ratio(0.55, points.state.J)
    assert e[1] > start["e"][1] + 0.05  # the stronger set dilated in shear
    assert start["e"][1] + 0.02 < hook.e_lagged[1] < e[1] - 0.01
    expected = mobilised_friction_deg(full["phi_g"], hook.e_lagged, points.mean(points.state.stress), 2.0, 0.7, 0.02,
                                      0.7, rule.p_ref)
    np.testing.assert_allclose(hook.friction_deg, expected, rtol=1e-12)


def test_a_friction_at_90_deg_falls_back_to_phi_mu_and_is_counted():
    """A point so dense that its mobilised friction reaches 90 deg steps with phi_mu instead, counted per point."""
    full = forward.full_parameters(SETS, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    per_set = {"m": np.array([1.5, 400.0]), "e_gamma": np.array([0.75, 0.75]), "lambda_c": np.array([0.05, 0.05])}
    hook = InterlockingFriction(Interlocking(), points.material, points.state, full["phi_g"], np.array([0.55, 0.55]),
                                per_set)
    assert hook.fallbacks.tolist() == [0, 1]
    assert hook.friction_deg[1] == full["phi_g"][1] and hook.friction_deg[0] > full["phi_g"][0]
    hook.advance(points.state)  # an accepted increment: counted again and logged for the run's diagnostics
    assert [(f.tolist(), b.tolist()) for f, b in hook.clip_log] == [([0, 0], [0, 2])]


def test_xi_per_set_in_one_batch():
    """forward.simulate reads xi_c per set: xi_c = 0.7 is the rule's default xi bit for bit; a batch of two xi runs
    each set as a run with that xi alone does; a larger xi at p above p_ref lowers e_c, so less strength."""
    test = replace(TEST, void_ratio=0.55, p0=3e5)
    rule = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.05)
    sets = {**{k: v for k, v in SETS.items() if k != "alpha0"}, "e_min": np.array([0.45, 0.45]),
            "e_max": np.array([0.7, 0.7])}
    base = forward.simulate(test, sets, SETTINGS, interlocking=rule)
    same = forward.simulate(test, {**sets, "xi_c": np.full(2, 0.7)}, SETTINGS, interlocking=rule)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(same.channel(name), base.channel(name))
    both = forward.simulate(test, {**sets, "xi_c": np.array([0.4, 1.0])}, SETTINGS, interlocking=rule)
    for i, xi in enumerate((0.4, 1.0)):
        alone = forward.simulate(test, sets, SETTINGS, interlocking=replace(rule, xi=xi))
        np.testing.assert_allclose(both.q[i], alone.q[i], rtol=1e-12)
    assert np.all(np.isfinite(both.q)) and both.q[0].max() > 1.01 * alone.q[0].max()
    with pytest.raises(ValueError, match="xi"):
        forward.simulate(test, {**sets, "xi_c": np.array([0.7, 1.5])}, SETTINGS, interlocking=rule)


def test_the_forward_model_counts_the_rules_clips_per_set():
    """``Curves.n_clip`` counts, per set, the increments whose friction fell back to phi_mu (m = 400: at every one)
    or whose e_c was floored (e_Gamma 0.06: e_c(p) below E_C_FLOOR once p passes about 0.035 p_ref); zero for a
    plain set and without the rule."""
    test = replace(TEST, void_ratio=0.55)
    sets = {**{k: np.repeat(v[:1], 3) for k, v in SETS.items() if k != "alpha0"},
            "e_min": np.full(3, 0.45), "e_max": np.full(3, 0.7), "interlocking_m": np.array([1.5, 400.0, 1.5]),
            "e_gamma": np.array([0.75, 0.75, 0.06])}
    curves = forward.simulate(test, sets, SETTINGS, interlocking=Interlocking(lambda_c=0.05))
    n_shear = round(EPS1[-1] / SETTINGS.increment)
    assert curves.n_clip[0] == 0
    assert curves.n_clip[1] >= n_shear and curves.n_clip[2] >= n_shear
    plain = forward.simulate(test, {k: v[:1] for k, v in sets.items() if k not in ("interlocking_m", "e_gamma")},
                             SETTINGS)
    assert plain.n_clip.tolist() == [0]
