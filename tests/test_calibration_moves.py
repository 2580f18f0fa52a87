"""hmodel calibrate --moves: stretch (the default) keeps the chains of before bit for bit, de (emcee's
differential-evolution mix) samples another seeded, resumable chain, a chain is resumed only with the moves
that made it, and de recovers a known truth away from the defaults inside its 95 % intervals."""

from __future__ import annotations

import json

import h5py
import numpy as np

from cli_checks import TOY_CALIBRATION, toy_biaxial_data

from homogenization.calibration.synthetic import synthetic_test, write_test
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

FAST = [*TOY_CALIBRATION, "--start", "prior"]


def _run(tmp_path, name: str, steps: int, *extra: str) -> int:
    return run_main(calibrate.main, [*toy_biaxial_data(tmp_path), *FAST, "--steps", str(steps),
                                     "--out", str(tmp_path / name), *extra])


def _chain(tmp_path, name: str) -> tuple[np.ndarray, np.ndarray, dict]:
    with h5py.File(tmp_path / name / "chain.h5", "r") as fh:
        return (np.array(fh["mcmc"]["chain"]), np.array(fh["mcmc"]["log_prob"]),
                json.loads(fh.attrs["calibration_config"]))


def test_default_moves_are_the_stretch_chain_bit_for_bit(tmp_path):
    """No --moves and --moves stretch: one chain, and its stored settings do not name the moves (so that the
    chains of earlier runs still resume)."""
    assert _run(tmp_path, "default", 3) == 0
    assert _run(tmp_path, "stretch", 3, "--moves", "stretch") == 0
    default, stretch = _chain(tmp_path, "default"), _chain(tmp_path, "stretch")
    assert np.isfinite(default[1]).all()
    assert np.array_equal(default[0], stretch[0]) and np.array_equal(default[1], stretch[1])
    assert default[2] == stretch[2] and "moves" not in default[2]


def test_de_samples_another_chain_that_resumes_bit_for_bit(tmp_path):
    """--moves de from the same start: other positions after the first step; recorded in chain.h5 and run.json;
    4 steps in two runs (the second resuming) are the 4 steps of one run."""
    assert _run(tmp_path, "stretch", 4) == 0
    assert _run(tmp_path, "de", 4, "--moves", "de") == 0
    assert _run(tmp_path, "de_resumed", 2, "--moves", "de") == 0
    assert _run(tmp_path, "de_resumed", 4, "--moves", "de") == 0
    stretch, de, resumed = (_chain(tmp_path, n) for n in ("stretch", "de", "de_resumed"))
    assert de[0].shape == stretch[0].shape == (4, 6, 2)
    assert not np.array_equal(de[0][0], stretch[0][0])
    assert np.isfinite(de[1]).all()
    assert np.array_equal(de[0], resumed[0]) and np.array_equal(de[1], resumed[1])
    assert de[2]["moves"] == "de"
    assert json.loads((tmp_path / "de" / "run.json").read_text())["config"]["moves"] == "de"


def test_resume_with_other_moves_is_refused_in_one_line(tmp_path, capsys):
    """A stretch chain resumed with --moves de, and a de chain resumed without --moves: exit 2 in one line, the
    chain untouched; --overwrite restarts it with the new moves."""
    assert _run(tmp_path, "a", 2) == 0
    assert _run(tmp_path, "b", 2, "--moves", "de") == 0
    capsys.readouterr()
    for name, extra in (("a", ("--moves", "de")), ("b", ())):
        before = _chain(tmp_path, name)[0]
        assert _run(tmp_path, name, 4, *extra) == 2
        lines = capsys.readouterr().err.splitlines()
        assert len(lines) == 1 and "other settings" in lines[0] and "moves" in lines[0], lines
        assert np.array_equal(_chain(tmp_path, name)[0], before)
    assert _run(tmp_path, "a", 3, "--moves", "de", "--overwrite") == 0
    chain, _, config = _chain(tmp_path, "a")
    assert chain.shape[0] == 3 and config["moves"] == "de"


TRUTH = {"phi_g": 22.0, "alpha0": 60.0}
"""Away from the defaults (phi 30 deg, alpha0 55 deg) and from the start of a prior draw."""


def test_de_recovers_a_known_truth_inside_its_95_percent_intervals(tmp_path):
    """Synthetic biaxial tests made by the calibration's own forward model (no discretisation error) at TRUTH with
    2 % noise, calibrated with --moves de from the least-squares start: each truth inside its 95 % interval, the
    interval narrow (the data constrain both), the walkers moving. On these data a 400-step chain puts the truth
    at 0.5 posterior sd in both parameters (docs/studies/calibration_sampler_moves.md)."""
    argv = ["--orientations", "12", "--confirm", "none", "--resolution", "off", "--params", "phi_g,alpha0",
            "--walkers", "8", "--steps", "60", "--moves", "de", "-q", "--out", str(tmp_path / "run")]
    settings = calibrate.forward_settings(calibrate.build_parser().parse_args(["--data", "x.csv", *argv]), 2)
    rng = np.random.default_rng(20)  # the noise of tests/test_calibration_known_truth.py's data
    eps1 = np.linspace(0.001, 0.02, 20)
    for kind, p0, channels in (("undrained", 5e4, ("q", "p")), ("drained", 3e4, ("q", "eps_v"))):
        test, _ = synthetic_test(kind, p0, eps1, channels, TRUTH, settings, 0.02, rng)
        write_test(tmp_path / f"{kind}.csv", test)
        argv += ["--data", str(tmp_path / f"{kind}.csv")]
    assert run_main(calibrate.main, argv) == 0
    posterior = json.loads((tmp_path / "run" / "posterior.json").read_text())
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    for name, value in TRUTH.items():
        lo, hi = posterior[name]["ci95"]
        assert lo <= value <= hi, (name, posterior[name])
        assert hi - lo < 1.0, (name, posterior[name])  # deg: the data, not the prior, set the interval
    assert run["config"]["moves"] == "de"
    assert run["sampler"]["acceptance_fraction"] > 0.1
