"""The calibration's forward model under the critical-state renewal (``ForwardSettings.critical_state``):
its population (per-cell contact laws and opening angles) runs the package's ``Renewal`` exactly."""

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking
from homogenization.element_test.points import material_points, orientation_set
from homogenization.material.critical_state import DEFAULTS, Renewal
from homogenization.material import opening_spread
from homogenization.material.density import default_map
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.hcell import plain_h_cell

SETTINGS = forward.ForwardSettings(increment=2e-3, iso_increment=1e-3, lebedev_order=5, n_spins=2,
                                   stress_rtol=1e-5, critical_state=DEFAULTS[3])
EPS1 = np.linspace(0.002, 0.04, 20)
TEST = Measurement("drained", Path("drained.csv"), True, 1e5, EPS1, {"q": np.zeros(20), "eps_v": np.zeros(20)}, dim=3)
SETS = {"phi_g": np.array([30.0, 36.0]), "kn": np.array([2e7, 5e7]), "kt_over_kn": np.array([0.8, 1.2]),
        "alpha0": np.array([49.0, 57.0])}


def _single(i: int) -> forward.Curves:
    """Set i run as the package runs one law: a scalar-law model, cells from the mesostructure at alpha0, the
    package's ``Renewal`` on the default map, the calibration's stages and solver."""
    law = ContactLaw(kn=float(SETS["kn"][i]), kt_over_kn=float(SETS["kt_over_kn"][i]), phi_g_deg=float(SETS["phi_g"][i]))
    model = make_cell_model("analytical", contact_law=law, radius=SETTINGS.radius, dim=3)
    meso = plain_h_cell(3, float(SETS["alpha0"][i]), SETTINGS.radius)
    orient = orientation_set(meso, n_orientations=SETTINGS.n_orientations, lebedev_order=SETTINGS.lebedev_order,
                             n_spins=SETTINGS.n_spins, staggered_spins=SETTINGS.staggered_spins)
    points = material_points(model, meso, 1, orient)
    points.renewal = Renewal(SETTINGS.critical_state, points.material, points.state, default_map(3))
    return forward.simulate_points(TEST, points, SETTINGS)


def test_population_renewal_is_the_package_rule_per_set():
    both = forward.simulate(TEST, SETS, SETTINGS)
    plain = forward.simulate(TEST, SETS, replace(SETTINGS, critical_state=None))
    for i in range(2):
        one = _single(i)
        for name in ("q", "p", "eps_v"):
            np.testing.assert_allclose(both.channel(name)[i], one.channel(name)[0], rtol=1e-9, atol=1e-9 * 1e5)
    # the rule acts on the loose set (alpha0 57 deg; the dense one renews at exp(-1.4 x 4) of the rate)
    assert np.max(np.abs(both.q[1] - plain.q[1])) > 0.02 * np.max(plain.q[1])


def _strain_path(n_points: int, steps: int = 40) -> list[SimpleNamespace]:
    """Drained-like states: eps1 in steps of 2e-3, laterals -0.7e-3 each (volume first down, then up), J from the
    normal strains (points alike)."""
    out = []
    for i in range(1, steps + 1):
        strain = np.zeros((n_points, 6))
        strain[:, 0], strain[:, 1:3] = 2e-3 * i, -0.7e-3 * i + 1e-5 * i * i
        out.append(SimpleNamespace(strain=strain, J=np.prod(1.0 - strain[:, :3], axis=1)))
    return out


def test_a_spread_point_renews_each_family_on_its_own_void_ratio():
    """alpha0_spread with the renewal: a point of spread s = 4 deg about 55 deg holds three families at 55 + 4 x_j;
    along one strain path each family renews, and at each fresh angle, as a point of one opening angle 55 + 4 x_j
    alone (the renewal's clock depends on the strain and J only): the spread point's renewals and clips are the
    families' sums, its fresh angles theirs. Shared e0 (the point's) would renew all three alike."""
    x, _ = opening_spread.nodes()
    full = forward.full_parameters({name: v[:1] for name, v in SETS.items()}, SETTINGS)
    full["alpha0"] = np.array([55.0])
    for name, default in zip(forward.DENSITY, forward.DENSITY_DEFAULTS):
        full[name] = np.full(1, default)
    spread = forward._renewal({**full, "alpha0_spread": np.array([4.0])}, SETTINGS,
                              forward.population({**full, "alpha0_spread": np.array([4.0])}, SETTINGS, 3))
    alone = []
    for xj in x:
        one = {**full, "alpha0": np.array([55.0 + 4.0 * xj])}
        alone.append(forward._renewal(one, SETTINGS, forward.population(one, SETTINGS, 3)))
    n = spread.material.orient.n_cells // 3
    for state in _strain_path(1):
        spread.advance(state)
        for r in alone:
            r.advance(state)
        angles = spread.cell_fresh_angle(state.J, np.array([0, n, 2 * n]))
        np.testing.assert_allclose(angles, [r.cell_fresh_angle(state.J, np.array([0]))[0] for r in alone], atol=1e-12)
    counts = [int(r.count[0]) for r in alone]
    assert int(spread.count[0]) == sum(counts) and len(set(counts)) == 3, counts
    assert int(spread.clipped[0]) == sum(int(r.clipped[0]) for r in alone)
    assert int(spread.capped[0]) == sum(int(r.capped[0]) for r in alone)


def test_a_spread_runs_with_the_renewal_and_the_interlocking():
    """forward.simulate with alpha0_spread, the renewal and the interlocking friction: spread 0 is the point of one
    opening angle (its cells three times over, to 1e-9), a spread of 3 deg another curve, its renewals counted."""
    rule = Interlocking(m=1.5, e_gamma=0.8, lambda_c=0.05, xi=0.5)
    one = forward.simulate(TEST, SETS, SETTINGS, interlocking=rule)
    zero = forward.simulate(TEST, {**SETS, "alpha0_spread": np.zeros(2)}, SETTINGS, interlocking=rule)
    three = forward.simulate(TEST, {**SETS, "alpha0_spread": np.full(2, 3.0)}, SETTINGS, interlocking=rule)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_allclose(zero.channel(name), one.channel(name), rtol=1e-9, atol=1e-9 * 1e5)
    assert np.max(np.abs(three.q[1] - one.q[1])) > 0.01 * np.max(one.q[1])
    assert np.all(np.isfinite(three.q)) and three.n_fallback.tolist() == [0, 0]


@pytest.mark.parametrize("phases, cell_spread, renewal", [("mirror-spin", 0.0, True), ("cell", 0.3, False)])
def test_spread_zero_is_one_opening_angle_whatever_rule_groups_the_cells(phases, cell_spread, renewal):
    """Spread 0 is the point of one opening angle (to 1e-9) also where the renewal's phases rank a cell's spins
    (mirror-spin) or the interlocking spreads the cells' friction (cell_spread): each family takes one family's
    phases and factors, not a share of three families' (which moved q by 40 % and 3.8 %)."""
    settings = replace(SETTINGS, critical_state=replace(DEFAULTS[3], phases=phases) if renewal else None)
    rule = Interlocking(m=1.5, e_gamma=0.8, lambda_c=0.05, xi=0.5, cell_spread=cell_spread) if cell_spread else None
    one = forward.simulate(TEST, SETS, settings, interlocking=rule)
    zero = forward.simulate(TEST, {**SETS, "alpha0_spread": np.zeros(2)}, settings, interlocking=rule)
    assert np.all(np.isfinite(one.q))
    for name in ("q", "p", "eps_v"):
        np.testing.assert_allclose(zero.channel(name), one.channel(name), rtol=1e-9, atol=1e-9 * 1e5)


def test_renewal_on_each_sets_own_void_ratio_map():
    """A test that gives its void ratio: each set runs at its map's alpha0 and renews on its own map, as the
    package's Renewal on that map alone; a set whose map misses the void ratio gets NaN."""
    e_min, e_max = np.array([0.55, 0.60, 0.80]), np.array([0.90, 1.00, 0.95])
    sets = {name: np.append(v, v[0]) for name, v in SETS.items() if name != "alpha0"}
    test = replace(TEST, void_ratio=0.75)
    curves = forward.simulate(test, {**sets, "e_min": e_min, "e_max": e_max}, SETTINGS)
    assert np.all(np.isnan(curves.q[2]))
    for i in range(2):
        law = ContactLaw(kn=float(sets["kn"][i]), kt_over_kn=float(sets["kt_over_kn"][i]),
                         phi_g_deg=float(sets["phi_g"][i]))
        model = make_cell_model("analytical", contact_law=law, radius=SETTINGS.radius, dim=3)
        density = default_map(3, e_min[i], e_max[i])
        meso = plain_h_cell(3, density.alpha0_deg(0.75), SETTINGS.radius)
        orient = orientation_set(meso, n_orientations=SETTINGS.n_orientations, lebedev_order=SETTINGS.lebedev_order,
                                 n_spins=SETTINGS.n_spins, staggered_spins=SETTINGS.staggered_spins)
        points = material_points(model, meso, 1, orient)
        points.renewal = Renewal(SETTINGS.critical_state, points.material, points.state, density)
        one = forward.simulate_points(test, points, SETTINGS)
        np.testing.assert_allclose(curves.q[i], one.q[0], rtol=1e-9, atol=1e-4)
        np.testing.assert_allclose(curves.eps_v[i], one.eps_v[0], rtol=1e-9, atol=1e-12)


def test_a_failed_set_does_not_stop_the_population():
    """A point whose J is not finite (its run failed) renews at alpha_c, flagged, instead of raising."""
    full = forward.full_parameters(SETS, SETTINGS)
    for name, default in zip(forward.DENSITY, forward.DENSITY_DEFAULTS):
        full[name] = np.full(2, default)
    points = forward.population(full, SETTINGS, 3)
    renewal = forward._renewal(full, SETTINGS, points)
    angle = renewal.fresh_angle(np.array([np.nan, 1.0]))
    assert angle[0] == SETTINGS.critical_state.alpha_c_deg and np.isfinite(angle[1])
    assert renewal.nonfinite.tolist() == [True, False]


def test_a_sets_curves_are_the_same_bits_alone_and_in_a_population():
    """``forward``'s promise: a point's curve does not depend on the population it runs in (V0 and the renewal's
    clock are sums per point, not BLAS products whose order depends on the number of points)."""
    rng = np.random.default_rng(7)
    sets = {name: np.concatenate([v, v[::-1]] * 3)[:6] * rng.uniform(0.98, 1.02, 6) for name, v in SETS.items()}
    together = forward.simulate(TEST, sets, SETTINGS)
    for i in (0, 3, 5):
        alone = forward.simulate(TEST, {name: v[i:i + 1] for name, v in sets.items()}, SETTINGS)
        for name in ("q", "p", "eps_v"):
            assert np.array_equal(together.channel(name)[i], alone.channel(name)[0], equal_nan=True), (i, name)


def test_the_renewals_clips_are_counted_per_set():
    """``Curves.n_renewal_clip``: the loose set renews at 20 exp(1.4 x 4) = 5400 per unit distortion, capped to
    rate_max 1000, with fresh cells of about 53 + 3 (57 - 53) = 65 deg clipped to alpha_max 62: both counted; fewer
    with alpha_max 75, none with rate_max 1e5 too; the dense set renews too slowly to clip here; no interlocking,
    so ``n_clip`` stays zero."""
    counts = []
    for changes in ({}, {"alpha_max_deg": 75.0}, {"alpha_max_deg": 75.0, "rate_max": 1e5}):
        rule = replace(DEFAULTS[3], **changes)
        curves = forward.simulate(TEST, SETS, replace(SETTINGS, critical_state=rule))
        assert curves.n_renewal_clip[0] == 0 and curves.n_clip.tolist() == [0, 0]
        counts.append(int(curves.n_renewal_clip[1]))
    assert counts[0] > counts[1] > counts[2] == 0, counts


def test_a_spread_past_the_cells_smallest_opening_at_the_maps_alpha0_gets_nan():
    """A test that gives its void ratio maps each set to its alpha0 first: a spread that takes the lowest family
    alpha0 - spread below 45 deg there gives that set NaN curves (a failed set), not an error for the population."""
    sets = {name: v for name, v in SETS.items() if name != "alpha0"}
    test = replace(TEST, void_ratio=0.60)  # the default map (0.597, 0.977) gives alpha0 47.07 deg
    curves = forward.simulate(test, {**sets, "alpha0_spread": np.array([2.0, 4.0])}, SETTINGS)
    assert np.all(np.isfinite(curves.q[0])) and np.all(np.isnan(curves.q[1]))
