"""hmodel calibrate where the truth is known: the forward model's resolution is checked and corrected, a
misfit far above the noise is said out loud, and the truth lies inside the 95 % intervals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from homogenization.calibration import bayes, resolution
from homogenization.calibration.data import read_test
from homogenization.calibration.forward import ForwardSettings
from homogenization.calibration.start import far_above_noise
from homogenization.calibration.synthetic import synthetic_test, write_test
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

TRUTH = {"phi_g": 26.5, "alpha0": 52.5}
ORIENTATIONS = 12
"""Orientations of the data and of the forward model: small, so that the test runs in seconds."""
TESTS = (("undrained", 5e4, ("q", "p")), ("drained", 3e4, ("q", "eps_v")))


def make_data(folder: Path, noise: float = 0.02, truth: dict | None = None) -> list[Path]:
    """The known-truth problem of benchmarks/bench_calibrate_truths.py, its source the closed form at a fine
    increment (5e-5) and 96 orientations (converged: the calibration refines towards the same curves)."""
    source = ForwardSettings(n_orientations=96, increment=5e-5, iso_increment=5e-5, stress_rtol=1e-5)
    rng = np.random.default_rng(20)
    eps1 = np.linspace(0.02 / 20, 0.02, 20)
    paths = []
    for kind, p0, channels in TESTS:
        test, _ = synthetic_test(kind, p0, eps1, channels, truth or TRUTH, source, noise, rng)
        paths.append(folder / f"{kind}.csv")
        write_test(paths[-1], test)
    return paths


def calibrate_run(paths: list[Path], out: Path, *extra: str) -> int:
    argv = ["--params", "phi_g,alpha0", "--walkers", "8", "--steps", "40", "--orientations", str(ORIENTATIONS),
            "--confirm", "none", "-q", "--out", str(out), *extra]
    for path in paths:
        argv += ["--data", str(path)]
    return run_main(calibrate.main, argv)


@pytest.mark.slow  # 20-33 s: the resolution check refines to 192 orientations at 3e-5 (also bench_calibrate_truths.py)
def test_known_truth_lies_inside_the_intervals_with_the_default_increment(tmp_path):
    """The default increment (1e-3) is several sigma away from the converged curves of these low-pressure
    tests: without the resolution check (and the start's further fits) the posterior misses the truth by
    many posterior standard deviations."""
    paths = make_data(tmp_path)
    assert calibrate_run(paths, tmp_path / "run") == 0
    posterior = json.loads((tmp_path / "run" / "posterior.json").read_text())
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    for name, value in TRUTH.items():  # within 3 posterior sd (the short chain's 95 % interval is itself noisy)
        lo, hi = posterior[name]["ci95"]
        assert abs(posterior[name]["mean"] - value) <= 3.0 * (hi - lo) / 3.92, (name, posterior[name])
    res = run["forward_model"]["resolution"]
    assert not res["levels"][0]["passed"] and res["levels"][0]["worst_rms_over_sigma"] > resolution.RMS_TOLERANCE
    assert res["refinements"] >= 1 and res["levels"][-1]["passed"] and res["reference"]["increment"] < 1e-3
    assert res["optimum"]["passed"]
    assert not run["misfit_against_noise"]["far_above_noise"]
    assert "converged" in run["sampler"]["autocorrelation"]
    start, limit = run["start"], far_above_noise(run["start"]["residuals"], len(TRUTH))
    chi_squares = [fit["chi_square"] for fit in start["fits"]]  # the first starts miss far above the noise here:
    assert 0 < start["more_fits"] < start["prior_draws"] - start["least_squares_starts"]  # more fits, not all draws,
    assert chi_squares[-1] <= limit < min(chi_squares[:-1]) and start["chi_square"] == chi_squares[-1]  # up to the first within
    check_band_is_corrected(tmp_path / "run")


def check_band_is_corrected(folder: Path) -> None:
    """The posterior band of a corrected calibration runs the same correction: at the posterior mean it is the
    reference model's curve, not the coarse model's (which is several sigma away on these tests)."""
    from dataclasses import replace  # noqa: PLC0415

    from homogenization.calibration.data import Measurement  # noqa: PLC0415
    from homogenization.calibration.forward import simulate  # noqa: PLC0415
    from homogenization.calibration.posterior import band, draw_samples, read_posterior  # noqa: PLC0415

    post = read_posterior(folder)
    assert post.reference is not None and post.reference.increment < post.forward.increment
    out = band(post, draw_samples(post, 16, 0), dim=2, drained=True, p0=3e4, eps_max=0.02)
    test = Measurement("band", post.path, True, 3e4, out.eps1, {}, 2)
    mean = {name: np.array([value]) for name, value in post.mean.items()}
    fine, coarse = simulate(test, mean, post.reference), simulate(test, mean, replace(post.forward))
    for c in ("q", "eps_v"):
        scale = np.max(np.abs(fine.channel(c)[0]))
        assert np.max(np.abs(out.columns[f"{c}_forward_at_mean"] - fine.channel(c)[0])) <= 1e-9 * scale
        assert np.max(np.abs(coarse.channel(c)[0] - fine.channel(c)[0])) > 0.01 * scale  # a correction that matters
    assert out.correction["eps_v"] > 0.0


def test_resolution_check_refuses_with_the_flags_to_set(tmp_path, capsys):
    """At a noise of 10 % the default increment is still too coarse (1.8 sigma); the check names its flags after
    three refinements (the default 2 % refines to 1.6e-5 and 192 orientations first: 11 s instead of 3 s)."""
    paths = make_data(tmp_path)
    assert calibrate_run(paths, tmp_path / "run", "--resolution", "check", "--start", "prior", "--noise", "0.1") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--increment" in err and "--orientations" in err
    assert not (tmp_path / "run" / "posterior.json").exists()
    assert not (tmp_path / "run" / "chain.h5").exists()  # a stamped empty chain blocked the rerun it recommends


def test_misfit_far_above_the_noise_is_measured_and_a_model_error_brings_it_to_one(tmp_path):
    """Data with 6 % noise calibrated with the default 2 %: the reduced chi-square at the truth is near 9, above
    the limit; the suggested model error, added in quadrature, brings it near 1."""
    tests = [read_test(p) for p in make_data(tmp_path, noise=0.06)]
    prior = bayes.make_prior(("phi_g", "alpha0"))
    settings = ForwardSettings(n_orientations=96, increment=5e-5, iso_increment=5e-5, stress_rtol=1e-5)
    x = prior.to_coord(np.array([TRUTH["phi_g"], TRUTH["alpha0"]]))
    fit = resolution.misfit(bayes.Posterior(tests, prior, settings, 0.02), x, 0.02)
    assert fit.far_above_noise and 5.0 < fit.reduced < 15.0
    assert "--model-error" in fit.warning(0.02)
    widened = resolution.misfit(bayes.Posterior(tests, prior, settings, float(np.hypot(0.02, fit.suggested_model_error))),
                                x, 0.02)
    assert not widened.far_above_noise and widened.reduced == pytest.approx(1.0, rel=0.05)
    honest = resolution.misfit(bayes.Posterior(tests, prior, settings, 0.06), x, 0.06)
    assert not honest.far_above_noise


def test_model_error_widens_sigma_in_quadrature_and_bad_values_exit_2(tmp_path, capsys):
    paths = make_data(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        calibrate_run(paths, tmp_path / "run", "--model-error", "-0.1")
    assert exit_info.value.code == 2 and "--model-error" in capsys.readouterr().err
    args = calibrate.build_parser().parse_args(["--data", "a", "--params", "phi_g", "--out", "o", "--noise", "0.03",
                                                "--model-error", "0.04"])
    assert calibrate.likelihood_noise(args) == pytest.approx(0.05)


def test_refined_settings_halve_the_increment_and_double_the_orientations():
    """In 3D both factors of the product rule: two Lebedev orders up and twice the spins (the spins alone, held at
    4, left a triaxial calibration biased past its interval: an audit's truth alpha0 = 62 outside [61.16, 61.85])."""
    s = ForwardSettings(n_orientations=36, increment=1e-3, iso_increment=5e-4, lebedev_order=11, n_spins=4)
    assert resolution.refined(s, "increment").increment == 5e-4
    assert resolution.refined(s, "increment").iso_increment == 2.5e-4
    finer = resolution.refined(s, "orientations")
    assert (finer.n_orientations, finer.lebedev_order, finer.n_spins, finer.increment) == (72, 15, 8, 1e-3)
    assert calibrate.RULE_FLAGS[3](finer) == "--order 15 --spins 8"  # what --resolution check names (not --orientations)
    assert calibrate.RULE_FLAGS[2](finer) == "--orientations 72"


def test_error_estimate_adds_the_knobs_richardson_scaled():
    """Truth 2 of benchmarks/bench_calibrate_truths.py: one refinement of each knob moves alpha0 by 0.27 and 0.12 sd
    and phi_g by 0.14 and 0.26 sd, each under the tolerance, yet the default model's optimum lies 0.7 sd from the
    converged one. The error estimate (2 x the increment's, 4/3 x the orientations', summed) fails the check."""
    rms = {"increment": {"d:q": 0.21, "d:eps_v": 0.07}, "orientations": {"d:q": 0.12, "d:eps_v": 0.12}}
    shift = {"increment": {"phi_g": -0.14, "alpha0": -0.27}, "orientations": {"phi_g": -0.26, "alpha0": -0.12}}
    check = resolution.Check("start", {}, {}, rms, rms, shift)
    assert check.worst_rms() < resolution.RMS_TOLERANCE and check.worst_shift() < resolution.SHIFT_TOLERANCE + 0.1
    assert check.error_shift()["alpha0"] == pytest.approx(2 * 0.27 + 4 / 3 * 0.12)
    assert check.error_rms()["d:q"] == pytest.approx(2 * 0.21 + 4 / 3 * 0.12)
    assert not check.passed and check.knobs_to_refine == ["increment", "orientations"]
    halved = {k: {n: v / 4 for n, v in d.items()} for k, d in shift.items()}
    assert resolution.Check("start", {}, {}, rms, rms, halved).error_shift()["alpha0"] < resolution.SHIFT_TOLERANCE
    against = resolution.Check("optimum", {}, {}, {"reference": {"d:q": 0.1}}, {"reference": {"d:q": 0.1}},
                               {"reference": {"alpha0": 0.15}})
    assert against.passed and against.error_shift()["alpha0"] == pytest.approx(0.15)
