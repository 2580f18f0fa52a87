"""hmodel calibrate --critical-state: the rule reaches the forward model, its alpha_c and renewal_rate are
calibratable, posterior.json records the rule at the posterior mean and hmodel biaxial --posterior runs it."""

from dataclasses import asdict, replace
from pathlib import Path

import json

import numpy as np
import pytest

from homogenization.calibration import bayes, forward
from homogenization.calibration import posterior as post_mod
from homogenization.calibration.data import Measurement
from homogenization.cli import calibrate, hmodel
from homogenization.material.critical_state import DEFAULTS
from homogenization.output import io
from tests.test_density import read_curve
from warp_hcell.core.cli import run_main

EPS1 = np.array([0.004, 0.008, 0.012])
SETTINGS = forward.ForwardSettings(n_orientations=4, increment=4e-3, iso_increment=2e-3)
FAST = ["--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none",
        "--resolution", "off", "-q"]
TEST = Measurement("u", Path("u.csv"), False, 2e5, EPS1, {"q": np.zeros(3)}, 2)


def _write(path: Path, q: np.ndarray) -> Path:
    rows = "\n".join(f"{x:g},{v:.9g}" for x, v in zip(EPS1, q))
    path.write_text(f"# test = undrained\n# p0 = 2e5\neps1,q\n{rows}\n")
    return path


def test_the_rules_parameters_reach_each_set():
    """alpha_c per set: each set's curve is the forward model's with that alpha_c as the rule's."""
    rule = replace(SETTINGS, critical_state=DEFAULTS[2])
    both = forward.simulate(TEST, {"alpha_c": np.array([48.0, 56.0])}, rule)
    for i, alpha_c in enumerate((48.0, 56.0)):
        one = forward.simulate(TEST, {"phi_g": np.array([SETTINGS.fixed["phi_g"]])},
                               replace(rule, critical_state=replace(DEFAULTS[2], alpha_c_deg=alpha_c)))
        np.testing.assert_allclose(both.q[i], one.q[0], rtol=1e-9)
    assert abs(both.q[0, 1] - both.q[1, 1]) > 0.1 * abs(both.q[1, 1])
    with pytest.raises(ValueError, match="critical-state rule"):
        forward.simulate(TEST, {"alpha_c": np.array([50.0])}, SETTINGS)


@pytest.fixture(scope="module")
def rule_posterior(tmp_path_factory):
    """A tiny calibration (4 walkers x 3 steps) of alpha_c on an undrained test made with the rule at 52 deg;
    returns its folder and the forward settings every log-posterior call saw."""
    folder = tmp_path_factory.mktemp("rule")
    truth = forward.simulate(TEST, {"alpha_c": np.array([52.0])}, replace(SETTINGS, critical_state=DEFAULTS[2])).q[0]
    data = _write(folder / "u.csv", truth)
    seen = []
    original = bayes.simulate

    def spy(test, params, settings):
        seen.append(settings.critical_state)
        return original(test, params, settings)

    bayes.simulate = spy
    try:
        out = folder / "cal"
        assert run_main(calibrate.main, ["--data", str(data), "--params", "alpha_c", "--critical-state", "--walkers",
                                         "4", "--steps", "3", *FAST, "--out", str(out)]) == 0
    finally:
        bayes.simulate = original
    return out, seen


def test_the_flag_reaches_the_forward_model_and_posterior_json(rule_posterior):
    out, seen = rule_posterior
    assert seen and all(rule == DEFAULTS[2] for rule in seen)
    data = json.loads((out / "posterior.json").read_text())
    mean = data["alpha_c"]["mean"]
    assert data["critical_state"] == asdict(replace(DEFAULTS[2], alpha_c_deg=mean))
    post = post_mod.read_posterior(out)
    assert post.forward.critical_state == replace(DEFAULTS[2], alpha_c_deg=mean)
    assert post.mean["alpha_c"] == mean


def test_a_posterior_with_the_rule_replays_with_it(rule_posterior, tmp_path):
    out, _ = rule_posterior
    post = post_mod.read_posterior(out)
    run = tmp_path / "run"
    assert hmodel.main(["biaxial", "--posterior", str(out), "--posterior-band", "4", "--orientations", "4",
                        "--eps-max", "0.012", "--increment", "4e-3", "--iso-increment", "2e-3", "--p0", "2e5", "-q",
                        "--out", str(run)]) == 0
    stored = io.read_run(run / io.RUN_FILE)
    assert stored.attrs["parameters"]["critical_state"]["alpha_c_deg"] == pytest.approx(post.mean["alpha_c"])
    # the command's curve is the calibration's forward model at the posterior mean (the rule applied)
    table = [line for line in (run / "posterior_band.csv").read_text().splitlines() if not line.startswith("#")]
    band = dict(zip(table[0].split(","), map(float, table[-1].split(","))))
    plain = forward.simulate(TEST, {"phi_g": np.array([SETTINGS.fixed["phi_g"]])}, SETTINGS).q[0, -1]
    q = read_curve(run / io.CURVE_FILE)["q"][-1]
    assert q == pytest.approx(band["q_forward_at_mean"], rel=1e-3)
    assert abs(q - plain) > 0.01 * abs(plain)


@pytest.mark.parametrize("flags, expected", [
    (["--params", "alpha_c"], "add --critical-state"),
    (["--params", "renewal_rate", "--critical-state", "--prior", "PRIOR"], "the prior of renewal_rate reaches"),
])
def test_bad_rule_flags_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    data = _write(tmp_path / "u.csv", np.array([1e5, 1.1e5, 1.2e5]))
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"renewal_rate": [1.0, 5000.0]}))
    flags = [str(prior) if f == "PRIOR" else f for f in flags]
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(data), *flags, "--walkers", "4", "--steps", "2", *FAST,
                                     "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and expected in lines[0], lines
    assert not out.exists()


def test_a_plain_posterior_refuses_the_critical_state(tmp_path, capsys):
    data = _write(tmp_path / "u.csv", forward.simulate(TEST, {"phi_g": np.array([30.0])}, SETTINGS).q[0])
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g", "--walkers", "4", "--steps", "2",
                                     "--start", "prior", *FAST, "--out", str(out)]) == 0
    assert "critical_state" not in json.loads((out / "posterior.json").read_text())
    capsys.readouterr()
    assert hmodel.main(["biaxial", "--posterior", str(out), "--critical-state", "--orientations", "4", "--eps-max",
                        "0.008", "--increment", "4e-3", "-q", "--out", str(tmp_path / "x")]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "calibrated without the critical-state rule" in lines[0], lines
    assert not (tmp_path / "x").exists()
