"""hmodel calibrate --interlocking: the interlocking friction reaches the forward model through its settings, its
parameters are calibrated per set, posterior.json holds it at the posterior mean, hmodel triaxial --posterior runs
it, bad combinations are one line and exit 2, and without the flag nothing changes."""

import json
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from cli_checks import assert_one_line_refusal, replayed_shear, interlocking_data

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import Interlocking
from homogenization.cli import calibrate
from homogenization.material.critical_state import DEFAULTS
from warp_hcell.core.cli import run_main

EPS1 = np.array([0.004, 0.008, 0.012])
SETTINGS = forward.ForwardSettings(lebedev_order=7, n_spins=2, increment=4e-3, iso_increment=2e-3, stress_rtol=1e-5)
RULE = Interlocking(m=1.5, e_gamma=0.8, lambda_c=0.05, xi=0.5, cell_spread=0.3)
TEST = Measurement("t", Path("t.csv"), True, 2e5, EPS1, {"q": np.zeros(3)}, 3, 0.6)
FAST = ["--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none", "--resolution", "off", "-q"]


def test_the_settings_friction_and_its_per_set_parameters_reach_the_forward_model():
    """settings.interlocking runs as the keyword does; a set's m in params overrides the settings' m (the other
    set keeps it); without the friction the curve is the plain one and the parameters are refused."""
    params = {"kn": np.array([3e7, 3e7]), "interlocking_m": np.array([RULE.m, 0.5])}
    with_settings = forward.simulate(TEST, params, replace(SETTINGS, interlocking=RULE))
    by_keyword = forward.simulate(TEST, params, SETTINGS, interlocking=RULE)
    np.testing.assert_array_equal(with_settings.q, by_keyword.q)
    at_half = forward.simulate(TEST, {"kn": np.array([3e7])}, replace(SETTINGS, interlocking=replace(RULE, m=0.5)))
    np.testing.assert_allclose(with_settings.q[1], at_half.q[0], rtol=1e-12)  # one batch against one set
    plain = forward.simulate(TEST, {"kn": np.array([3e7])}, SETTINGS)
    assert abs(with_settings.q[0, -1] - plain.q[0, -1]) > 0.05 * plain.q[0, -1]  # past the elastic start
    assert abs(with_settings.q[0, -1] - with_settings.q[1, -1]) > 0.02 * plain.q[0, -1]
    with pytest.raises(ValueError, match="interlocking friction"):
        forward.simulate(TEST, params, SETTINGS)


def test_without_the_friction_the_records_read_as_before():
    assert "interlocking" not in forward.settings_record(SETTINGS)
    assert forward.settings_record(replace(SETTINGS, interlocking=RULE))["interlocking"]["xi"] == RULE.xi


@pytest.mark.parametrize("flags, data, expected", [
    (["--params", "phi_g,interlocking_m"], "triaxial_drained", "add --interlocking"),
    (["--params", "phi_g", "--interlocking-values", "xi_c=0.5"], "triaxial_drained", "add --interlocking"),
    (["--params", "phi_g", "--interlocking"], "drained", "needs triaxial data"),
    (["--params", "phi_g", "--interlocking", "--confirm", "dem"], "triaxial_drained", "--confirm dem runs the DEM"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "xi_c=1.5"], "triaxial_drained",
     "xi = 1.5 is out of range"),
    (["--params", "phi_g", "--interlocking", "--interlocking-values", "m=1"], "triaxial_drained",
     "is not NAME=VALUE"),
    (["--params", "phi_g,cell_spread", "--interlocking", "--prior", "PRIOR"], "triaxial_drained",
     "the prior of cell_spread reaches 1.2"),
    (["--params", "phi_g,kn", "--start-point", "phi_g=30"], "triaxial_drained", "missing kn"),
    (["--params", "phi_g", "--start-point", "phi_g=30", "--start", "prior"], "triaxial_drained", "--start prior"),
])
def test_bad_flags_exit_2_before_any_run(tmp_path, capsys, flags, data, expected):
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"cell_spread": [0.0, 1.2]}))
    flags = [str(prior) if f == "PRIOR" else f for f in flags]
    out = tmp_path / "cal"
    args = ["--data", str(interlocking_data(tmp_path / "t.csv", data)), *flags, "--walkers", "4", "--steps", "2",
            "--out", str(out)]
    args += [f for f in FAST if f not in ("--confirm", "none") or "--confirm" not in flags]
    assert_one_line_refusal(capsys, calibrate.main, args, expected, out)


def test_the_posterior_holds_the_friction_and_triaxial_replays_it(tmp_path):
    """posterior.json's ``interlocking`` is the friction at the posterior mean (calibrated m and spread, the
    --interlocking-values elsewhere); hmodel triaxial --posterior runs it (and the critical-state renewal inside it)
    as the calibration's forward model does, far from the plain cell's curve. The map start from --start-point is
    recorded (run.json's start: ``refit_from``)."""
    out = tmp_path / "cal"
    assert run_main(calibrate.main, [
        "--data", str(interlocking_data(tmp_path / "t.csv")), "--params", "phi_g,interlocking_m,cell_spread",
        "--critical-state",
        "--interlocking", "--interlocking-values", "e_gamma=0.8,xi_c=0.5", "--walkers", "6", "--steps", "2",
        "--start-point", "phi_g=30,interlocking_m=1.5,cell_spread=0.3", *FAST, "--out", str(out)]) == 0
    data = json.loads((out / "posterior.json").read_text())
    run = json.loads((out / "run.json").read_text())
    assert run["start"]["refit_from"] == {"phi_g": 30.0, "interlocking_m": 1.5, "cell_spread": 0.3}
    assert data["interlocking"] == {**vars(Interlocking(e_gamma=0.8, xi=0.5)), "m": data["interlocking_m"]["mean"],
                                    "cell_spread": data["cell_spread"]["mean"]}
    from homogenization.calibration import posterior as post_mod  # noqa: PLC0415

    post = post_mod.read_posterior(out)
    assert post.forward.interlocking == Interlocking(**data["interlocking"])
    eps1, q = replayed_shear(out, tmp_path / "run")
    test = replace(TEST, eps1=eps1, observed={"q": q})
    mean = {name: np.array([value]) for name, value in post.mean.items()}
    expected = forward.simulate(test, mean, post.forward).q[0]
    np.testing.assert_allclose(q, expected, rtol=1e-4)
    plain = forward.simulate(test, {k: v for k, v in mean.items() if k not in forward.INTERLOCKING},
                             replace(post.forward, interlocking=None)).q[0]
    assert abs(q[-1] - plain[-1]) > 0.1 * plain[-1]
    assert post.forward.critical_state == DEFAULTS[3]
    assert run["forward_model"]["interlocking_clips"] == 0  # counted (none at these states), as the fallbacks
    with h5py.File(tmp_path / "run" / "run.h5") as f:  # the replay counts the rule's clips per increment too
        counts = {name: f["diagnostics"][f"interlocking_{name}"][()] for name in ("floored", "fallbacks")}
        renewals = f["diagnostics"]["critical_state_renewals"][()]
    for values in counts.values():
        assert values.shape == renewals.shape and np.nanmax(values) == 0 and np.isfinite(values).sum() >= 4


def test_the_orientation_rule_flags_reach_the_forward_model(tmp_path, capsys):
    """--order, --spins and --staggered-spins set the triaxial rule (defaults: the forward model's 11 x 4 aligned,
    unchanged); an order outside the Lebedev rules is one line, exit 2."""
    data = str(interlocking_data(tmp_path / "t.csv"))
    parser = calibrate.build_parser()
    default = calibrate.forward_settings(parser.parse_args(["--data", data, "--params", "phi_g", "--out", "x"]), 3)
    assert (default.lebedev_order, default.n_spins, default.staggered_spins) == (11, 4, False)
    given = calibrate.forward_settings(parser.parse_args(["--data", data, "--params", "phi_g", "--out", "x", "--order",
                                                          "15", "--spins", "8", "--staggered-spins"]), 3)
    assert (given.lebedev_order, given.n_spins, given.staggered_spins) == (15, 8, True)
    with pytest.raises(SystemExit) as exc:
        run_main(calibrate.main, ["--data", data, "--params", "phi_g", "--order", "12", "--out", str(tmp_path / "c")])
    assert exc.value.code == 2 and "Lebedev order 12 is not one of" in capsys.readouterr().err


def test_a_spread_is_calibrated_with_the_renewal_and_replayed_family_by_family(tmp_path):
    """--params alpha0_spread with --critical-state --interlocking: the calibration runs the density families (each
    renewed on its own void ratio) and hmodel triaxial --posterior --void-ratio replays them about the map's alpha0 as
    the forward model does at the posterior mean; the point of one opening angle is another curve."""
    out = tmp_path / "cal"
    assert run_main(calibrate.main, [
        "--data", str(interlocking_data(tmp_path / "t.csv")), "--params", "phi_g,alpha0_spread", "--critical-state",
        "--interlocking", "--interlocking-values", "e_gamma=0.8,xi_c=0.5", "--e-min", "0.45", "--e-max", "0.7",
        "--walkers", "4", "--steps", "2", "--start-point", "phi_g=30,alpha0_spread=3", *FAST, "--out", str(out)]) == 0
    from homogenization.calibration import posterior as post_mod  # noqa: PLC0415

    post = post_mod.read_posterior(out)
    assert post.mean["alpha0_spread"] > 0.5
    eps1, q = replayed_shear(out, tmp_path / "run")
    test = replace(TEST, eps1=eps1, observed={"q": q})
    mean = {name: np.array([value]) for name, value in post.mean.items()}
    settings = replace(post.forward, lebedev_order=11, n_spins=4, staggered_spins=False)
    expected = forward.simulate(test, mean, settings).q[0]
    np.testing.assert_allclose(q, expected, rtol=1e-4)
    single = forward.simulate(test, {k: v for k, v in mean.items() if k != "alpha0_spread"}, settings).q[0]
    assert np.max(np.abs(q - single)) > 1e-3 * np.max(single), np.max(np.abs(q - single)) / np.max(single)
    with h5py.File(tmp_path / "run" / "run.h5") as f:
        assert np.nansum(f["diagnostics"]["critical_state_renewals"][()]) > 0
