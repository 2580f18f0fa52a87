"""Where the walkers of hmodel calibrate start (``homogenization.calibration.start``): the seeded
multi-start least-squares fit of --start map on the shipped synthetic data, its Laplace ball, and
the command's record of it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from homogenization.calibration import bayes, start
from homogenization.calibration.data import read_test
from homogenization.calibration.report import STUCK_LOG_POSTERIOR
from homogenization.cli import calibrate
from homogenization.cli.hmodel import run_main

DATA = Path(__file__).resolve().parent / "data" / "calibration"
TRUTH = json.loads((DATA / "truth.json").read_text())
COARSE = replace(calibrate.FORWARD, n_orientations=12, increment=2e-3, iso_increment=1e-3)
"""A coarse forward model, so that the start runs in seconds (its bias: a few tenths of a degree)."""


def synthetic_posterior(settings=COARSE) -> bayes.Posterior:
    tests = [read_test(DATA / "undrained.csv"), read_test(DATA / "drained.csv")]
    prior = bayes.make_prior(tuple(TRUTH), dim=2)
    return bayes.Posterior(tests, prior, settings, 0.02)


def test_map_start_lands_near_the_truth_of_the_synthetic_data():
    """Measured: phi_g 25.52 deg, kn 3.023e8 N/m, kt/kn 0.6014, alpha0 58.44 deg (truth 26, 3e8, 0.6, 58),
    chi-square 132 over 100 residuals, from 16 prior draws whose best had a chi-square in the thousands."""
    log_post = synthetic_posterior()
    walkers, record = start.map_start(log_post, 8, np.random.default_rng(0))
    best = record["optimum"]
    assert abs(best["phi_g"] - TRUTH["phi_g"]) <= 1.5 and abs(best["alpha0"] - TRUTH["alpha0"]) <= 2.0
    assert best["kn"] == pytest.approx(TRUTH["kn"], rel=0.05)
    assert best["kt_over_kn"] == pytest.approx(TRUTH["kt_over_kn"], rel=0.05)
    # the fit improved on the best prior draw, to about one sigma per residual (2 % noise, unbiased model)
    assert record["chi_square"] < 0.1 * record["chi_square_best_prior_draw"]
    assert record["chi_square"] < 2.0 * record["residuals"]
    assert record["evaluations"] >= start.MAP_DRAWS and record["failed_sets"] == 0
    # every walker starts in the main mode: none would be left out as stuck
    lp = log_post(walkers)
    assert walkers.shape == (8, 4) and np.all(np.isfinite(lp))
    assert np.max(lp) - np.min(lp) < STUCK_LOG_POSTERIOR


def test_map_start_is_reproducible_from_its_seed():
    cheap = replace(COARSE, n_orientations=4, increment=4e-3, iso_increment=2e-3)  # the same code, fewer cells
    a, ra = start.map_start(synthetic_posterior(cheap), 6, np.random.default_rng(4))
    b, rb = start.map_start(synthetic_posterior(cheap), 6, np.random.default_rng(4))
    np.testing.assert_array_equal(a, b)
    assert ra == rb


def test_laplace_draws_have_the_inverse_curvature_as_covariance_capped_where_flat():
    rng = np.random.default_rng(1)
    jac = np.array([[2000.0, 0.0, 0.0], [1500.0, 1000.0, 0.0], [0.0, 0.0, 1.0]])  # third direction nearly flat
    draws = start.laplace_draws(jac, rng, 40000)
    cov = np.linalg.inv(jac[:2, :2].T @ jac[:2, :2])
    np.testing.assert_allclose(np.cov(draws[:, :2], rowvar=False), cov, rtol=0.05, atol=0.05 * np.max(np.abs(cov)))
    assert np.std(draws[:, 2]) == pytest.approx(start.MAP_BALL, rel=0.03)


def tiny(tmp_path: Path, *extra: str) -> dict:
    data = tmp_path / "u.csv"
    data.write_text("# test = undrained\n# p0 = 3e6\neps1,q\n0.004,1.1e6\n0.008,1.8e6\n0.012,2.2e6\n")
    out = tmp_path / "_".join(extra or ("default",))
    code = run_main(calibrate.main, ["--data", str(data), "--params", "phi_g,alpha0", "--walkers", "4", "--steps", "2",
                                     "--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3",
                                     "--confirm", "none", "-q", "--out", str(out), *extra])
    assert code == 0
    return json.loads((out / "run.json").read_text())


def test_the_command_records_its_start(tmp_path):
    default, prior = tiny(tmp_path), tiny(tmp_path, "--start", "prior")
    assert default["start"]["method"] == "map" and default["config"]["start"] == "map"
    assert default["start"]["evaluations"] > start.MAP_DRAWS and set(default["start"]["optimum"]) == {"phi_g", "alpha0"}
    counts = prior["start"]["forward_counts"]  # the prior draws and the resolution check's runs
    assert prior["start"] == {"method": "prior", "prior_draws": 32, "seconds": prior["start"]["seconds"],
                              "forward_counts": counts} and counts["evaluations"] >= 32
    assert default["start"]["chi_square"] <= default["start"]["chi_square_best_prior_draw"]
