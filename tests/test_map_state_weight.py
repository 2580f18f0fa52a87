"""The interlocking's state map (``map_state_weight`` w: a test's cell built at the void-ratio map's alpha0 of
e_map = e0 + w lambda_c ((p0 / p_ref)^xi_c - 1), ``interlocking.state_map_void_ratio``, ``forward.density_alpha0``):
hand values, w = 0 bit for bit, per set in the forward model, the friction still reading e0, NaN curves where e_map
leaves the map, replayed by hmodel triaxial --posterior, refused in one line where it cannot act."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_interlocking_refusal, assert_one_line_refusal
from interlocking_cases import FAST, P_REF, SETS, SETTINGS, calibrated_replay

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking, state_map_void_ratio

EPS1 = np.linspace(0.002, 0.04, 20)
RULE = Interlocking(m=2.0, e_gamma=0.7, lambda_c=0.04, xi=0.5)
"""lambda_c 0.04, xi 0.5: at p0 = 4 p_ref, (p0 / p_ref)^xi - 1 = 1, so e_map = e0 + 0.04 w."""


def drained(void_ratio: float | None, p0: float = 4 * P_REF) -> Measurement:
    """A drained test at ``p0`` [Pa] to 4 % of the given initial void ratio (its curves are not read)."""
    return Measurement("drained", Path("drained.csv"), True, p0, EPS1, {"q": np.zeros(20), "eps_v": np.zeros(20)},
                       dim=3, void_ratio=void_ratio)


def alpha_of(e: float, e_min: float = 0.45, e_max: float = 0.7) -> float:
    """The 3D map's alpha0 [deg] of void ratio ``e`` by hand: 55.3 deg at e_max, 47 deg at e_min, linear between."""
    return 55.3 - (e_max - e) / (e_max - e_min) * (55.3 - 47.0)


def test_the_mapped_void_ratio_by_hand_and_its_range():
    """e0 + w lambda ((p0 / p_ref)^xi - 1): 0.6 + 0.5 x 0.04 x (2 - 1) = 0.62 at 4 p_ref, xi 0.5; 0.6 - 0.02 at p_ref
    / 4 with w 1 (0.6 + 0.02 with w -1); exactly e0 at w = 0 (NaN line included) and at p0 = p_ref; w outside [-2, 2]
    refused, by the rule and per set by density_alpha0."""
    assert Interlocking().map_state_weight == 0.0
    assert state_map_void_ratio(0.6, 4 * P_REF, 0.5, 0.04, 0.5, P_REF) == pytest.approx(0.62, abs=1e-15)
    assert state_map_void_ratio(0.6, P_REF / 4, 1.0, 0.04, 0.5, P_REF) == pytest.approx(0.58, abs=1e-15)
    assert state_map_void_ratio(0.6, P_REF / 4, -1.0, 0.04, 0.5, P_REF) == pytest.approx(0.62, abs=1e-15)
    assert state_map_void_ratio(0.6, 4 * P_REF, 0.0, np.nan, 0.5, P_REF) == 0.6
    assert state_map_void_ratio(0.6, P_REF, 2.0, 0.04, 0.5, P_REF) == 0.6
    replace(Interlocking(), map_state_weight=-2.0).check()
    for value in (-2.1, 2.1):
        with pytest.raises(ValueError, match="map_state_weight"):
            replace(Interlocking(), map_state_weight=value).check()
        with pytest.raises(ValueError, match=f"map_state_weight = {value:g} is out of range"):
            forward.density_alpha0(drained(0.6), {**SETS, "map_state_weight": np.array([0.0, value])},
                                   replace(SETTINGS, interlocking=RULE))


def test_density_alpha0_moves_by_the_formula_per_set():
    """At e0 0.6, p0 4 p_ref, [e_min, e_max] = [0.45, 0.7]: w = 0 is alpha_of(0.6) = 51.98 deg, w = 0.5 alpha_of(0.62)
    = 52.644 deg (hand values); w from the interlocking or per set, lambda_c and xi_c per set read; a test without a
    void ratio has no mapped alpha0."""
    settings = replace(SETTINGS, interlocking=RULE)
    assert alpha_of(0.6) == pytest.approx(51.98, abs=1e-12) and alpha_of(0.62) == pytest.approx(52.644, abs=1e-12)
    test = drained(0.6)
    np.testing.assert_allclose(forward.density_alpha0(test, SETS, settings), [51.98, 51.98], atol=1e-12)
    per_set = {**SETS, "map_state_weight": np.array([0.0, 0.5])}
    np.testing.assert_allclose(forward.density_alpha0(test, per_set, settings), [51.98, 52.644], atol=1e-12)
    fixed = replace(settings, interlocking=replace(RULE, map_state_weight=0.5))
    np.testing.assert_allclose(forward.density_alpha0(test, SETS, fixed), [52.644, 52.644], atol=1e-12)
    # lambda_c 0.08 (per set) doubles the shift; xi_c 1 makes (p0 / p_ref)^xi - 1 = 3: 0.6 + 0.25 x 0.08 x 3 = 0.66
    line = {**per_set, "lambda_c": np.array([0.08, 0.08]), "xi_c": np.array([0.5, 1.0]),
            "map_state_weight": np.array([0.5, 0.25])}
    np.testing.assert_allclose(forward.density_alpha0(test, line, settings), [alpha_of(0.64), alpha_of(0.66)],
                               atol=1e-12)
    assert forward.density_alpha0(drained(None), per_set, settings) is None


def test_zero_weight_is_bit_for_bit_and_the_friction_reads_the_real_e0():
    """w = 0 per set is the run without it bit for bit; a set at w = 0.5 differs and is the w = 0 set on a map lowered
    by the shift 0.02 (same alpha0, same e0 for the friction: 1e-9); a set whose e_map leaves the map gets NaN curves
    (the other set's unchanged)."""
    test = drained(0.6)
    settings = replace(SETTINGS, interlocking=RULE)
    plain = forward.simulate(test, SETS, settings)
    zero = forward.simulate(test, {**SETS, "map_state_weight": np.zeros(2)}, settings)
    for name in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(zero.channel(name), plain.channel(name))
    moved = forward.simulate(test, {**SETS, "map_state_weight": np.array([0.0, 0.5])}, settings)
    np.testing.assert_array_equal(moved.q[0], plain.q[0])
    assert np.max(np.abs(moved.q[1] - plain.q[1])) > 0.01 * np.max(plain.q[1])
    lowered = forward.simulate(test, {**SETS, "e_min": np.full(2, 0.43), "e_max": np.full(2, 0.68)}, settings)
    np.testing.assert_allclose(moved.q[1], lowered.q[1], rtol=1e-9)
    np.testing.assert_allclose(moved.eps_v[1], lowered.eps_v[1], rtol=1e-9, atol=1e-12)
    # e_map = 0.6 + 2 x 0.04 = 0.68 is held, 0.6 + 2 x 0.08 = 0.76 is not: NaN curves, like an out-of-map void ratio
    out = forward.simulate(test, {**SETS, "map_state_weight": np.array([2.0, 2.0]), "lambda_c": np.array([0.04, 0.08])},
                           settings)
    assert np.all(np.isfinite(out.q[0])) and np.all(np.isnan(out.q[1])) and np.all(np.isnan(out.eps_v[1]))


@pytest.mark.parametrize("flags, data, expected", [
    (["--params", "phi_g,map_state_weight"], "given",
     "--params map_state_weight moves the map along the interlocking's critical-state line (lambda_c, xi_c); add "
     "--interlocking"),
    (["--params", "phi_g", "--interlocking-values", "map_state_weight=0.5"], "given", "add --interlocking"),
    (["--params", "phi_g,map_state_weight", "--interlocking"], "none",
     "map_state_weight shifts the void ratio that the map reads: --data"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "map_state_weight=0.5"], "none",
     "gives none ('# void_ratio = E'"),
    (["--params", "phi_g,map_state_weight", "--interlocking", "--interlocking-values", "lambda_c=0"], "given",
     "flat at lambda_c = 0: calibrate lambda_c or give it"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "map_state_weight=3"], "given",
     "map_state_weight = 3 is out of range"),
    (["--params", "phi_g,map_state_weight", "--interlocking", "--prior", "PRIOR"], "given",
     "the prior of map_state_weight reaches -2.5"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, data, expected):
    assert_interlocking_refusal(tmp_path, capsys, flags, data, expected, {"map_state_weight": [-2.5, 1.0]}, FAST)


def test_the_posterior_holds_the_weight_and_triaxial_replays_it(tmp_path, capsys):
    """posterior.json's interlocking holds the mean's map_state_weight; hmodel triaxial --posterior at void ratio 0.6
    and 200 kPa runs it as the forward model does (1e-4), apart from the curve at w = 0; a void ratio whose e_map
    leaves the posterior's map is refused in one line, exit 2."""
    from homogenization.cli import triaxial  # noqa: PLC0415

    post, data, q, model, without = calibrated_replay(tmp_path, "map_state_weight", "e_gamma=0.9,lambda_c=0.1,xi_c=0.5",
                                                      1.0, prior=(0.8, 1.2))
    assert post.forward.interlocking.map_state_weight == data["map_state_weight"]["mean"] >= 0.8
    np.testing.assert_allclose(q, model, rtol=1e-4)
    assert np.max(np.abs(q - without) / without) > 0.02
    out = tmp_path / "refused"
    capsys.readouterr()  # the calibration's warnings
    assert_one_line_refusal(capsys, triaxial.main, [
        "--posterior", str(tmp_path / "cal"), "--void-ratio", "0.95", "--drained", "--p0", "2e5", "--eps-max", "0.012",
        "--increment", "4e-3", "-q", "--out", str(out)], "the state map of --posterior", out)
