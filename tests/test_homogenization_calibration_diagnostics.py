"""The sampler's diagnostics of hmodel calibrate: autocorrelation time, effective sample size, the
warning of a chain too short to trust them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from homogenization.calibration import diagnostics, report
from tests.test_homogenization_calibration import tiny_run


def ar1_chain(rho: float, n_steps: int, n_walkers: int, seed: int = 0) -> np.ndarray:
    """Independent AR(1) walkers x_t = rho x_{t-1} + e_t, started stationary: integrated
    autocorrelation time (1 + rho) / (1 - rho) steps; shape (n_steps, n_walkers, 1)."""
    rng = np.random.default_rng(seed)
    x = np.empty((n_steps, n_walkers))
    x[0] = rng.standard_normal(n_walkers) / math.sqrt(1.0 - rho * rho)
    for t in range(1, n_steps):
        x[t] = rho * x[t - 1] + rng.standard_normal(n_walkers)
    return x[:, :, None]


def test_tau_and_ess_of_a_chain_of_known_autocorrelation():
    rho = 0.8  # tau = 1.8 / 0.2 = 9 steps
    diag = diagnostics.chain_diagnostics(ar1_chain(rho, 4000, 8), ["a"])
    tau = diag["tau_steps"]["a"]
    assert tau == pytest.approx(9.0, rel=0.15)
    assert diag["samples"] == 4000 * 8
    assert diag["effective_samples"]["a"] == pytest.approx(diag["samples"] / tau, rel=1e-12)
    assert diag["effective_samples"]["a"] <= diag["samples"]
    assert diag["steps_per_tau"] == pytest.approx(4000 / tau) and not diag["short"]
    assert diagnostics.warning_line(diag, 8000, 0.5) is None


def test_a_short_chain_is_flagged_with_advice():
    diag = diagnostics.chain_diagnostics(ar1_chain(0.95, 200, 8), ["a"])  # tau ~ 39 steps: ~5 tau
    assert diag["short"] and diag["steps_per_tau"] < diagnostics.STEPS_PER_TAU
    line = diagnostics.warning_line(diag, 400, 0.5)
    assert "short" in line and "--steps" in line and "\n" not in line
    steps = int(line.split("--steps ")[1].split()[0])
    assert steps >= 2 * 50 * diag["tau_steps"]["a"]  # 50 tau retained after a burn-in of half


def test_a_parameter_that_never_moved_has_no_tau():
    chain = np.concatenate([ar1_chain(0.5, 300, 4), np.ones((300, 4, 1))], axis=2)
    diag = diagnostics.chain_diagnostics(chain, ["a", "b"])
    assert diag["tau_steps"]["b"] is None and diag["effective_samples"]["b"] is None
    assert diag["tau_steps"]["a"] is not None and diag["short"]
    assert diag["walkers_that_never_moved"] == {"a": 0, "b": 4}
    assert "cannot be estimated" in diagnostics.warning_line(
        diagnostics.chain_diagnostics(np.ones((10, 4, 1)), ["b"]), 20, 0.5)


def test_a_short_calibration_warns_and_writes_its_diagnostics(tmp_path, capsys):
    assert tiny_run(tmp_path, "run", 12) == 0
    err = capsys.readouterr().err
    short = [line for line in err.strip().splitlines() if "the chain is short" in line]
    assert "--steps" in err and len(short) == 1  # (the misfit of these three points may warn too)
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    sampler = run["sampler"]
    line = next(x for x in report.summary_lines(run) if x.startswith("autocorrelation time"))
    assert f"of {sampler['autocorrelation']['samples']} samples" in line and "phi_g" in line
    auto = sampler["autocorrelation"]
    assert auto["short"] and auto["steps_retained"] == 6
    assert auto["samples"] == (4 - sampler["stuck_walkers_left_out"]) * 6 == sampler["retained_samples"]
    for name in ("phi_g", "alpha0"):
        tau, ess = auto["tau_steps"][name], auto["effective_samples"][name]
        assert math.isfinite(tau) and tau > 0.0
        assert 0.0 < ess <= auto["samples"]
