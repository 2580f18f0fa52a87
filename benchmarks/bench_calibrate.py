"""python benchmarks/bench_calibrate.py [--params phi_g,kn,kt_over_kn,alpha0] [--walkers 32] [--steps 500] [--out runs/bench_calibrate]
python benchmarks/bench_calibrate.py --coverage 20 [--steps 600] [--laplace] [--increment 1e-3 --stress-rtol 1e-5] [--results FILE]

Acceptance benchmark of ``hmodel calibrate`` (issue 20) on the synthetic DEM curves of
tests/data/calibration/ (made by make_synthetic.py at the values of truth.json, which the
calibration is not told; 2 % noise):

1. the error the coarse forward model adds (the calibration's default orientations, increments
   and stress tolerance) against a fine one (360 orientations, increments 1e-4, tolerance 1e-5),
   at the true parameters, as a fraction of the likelihood's sigma of each channel;
2. the calibration itself (a subprocess, timed, with the CPU time and the load average): per
   parameter the posterior mean, its error against the truth (relative; degrees for phi_g and
   alpha0), whether the truth lies in the 95 % interval, and the acceptance verdict (within 5 %,
   1.5 deg for phi_g, 2 deg for alpha0, for each constrained parameter); the wall time against
   the 15-minute budget. The machine may be shared: read the timings with the load average.

``--coverage N`` instead measures the empirical coverage of the 95 % intervals: N noise
realisations of the two tests, each the closed form at the DEM run's settings (``SYNTHETIC``,
which reproduces the DEM curves of the shipped files to below 1e-3 sigma) at the truth plus Gaussian noise drawn as
make_synthetic.py draws it (``NOISE`` x the clean channel's largest abs value, independent
per point), each calibrated as ``hmodel calibrate`` does (its default forward model, prior,
initial walkers, burn-in and stuck-walker rule; no figures, no DEM confirmation;
``--increment`` and ``--stress-rtol`` change its forward model). It prints and
writes, per parameter, how many truths fall inside the 95 % interval, and per realisation the
posterior and diagnostics. ``--laplace`` replaces each chain by the Gauss-Newton fit and its
interval fit +- 1.96 sd, sd = sqrt(diag (J^T J)^-1): many realisations in minutes, a check of
the forward model's and the Gaussian approximation's share of a coverage shortfall.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from homogenization.calibration import bayes
from homogenization.calibration.data import Measurement, read_test
from homogenization.calibration.forward import LAW_PARAMETERS, ForwardSettings, simulate
from homogenization.calibration.report import retained_samples
from homogenization.calibration.start import prior_start
from homogenization.cli.calibrate import FORWARD

PARAMETERS = LAW_PARAMETERS["linear"]
"""The linear law's parameters, all calibrated by this benchmark."""

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "calibration"
TESTS = ("undrained.csv", "drained.csv")
TOLERANCE = {"phi_g": ("deg", 1.5), "alpha0": ("deg", 2.0), "kn": ("rel", 0.05), "kt_over_kn": ("rel", 0.05)}
"""Acceptance of the posterior mean: absolute [deg] or relative [-] error allowed."""
BUDGET_S = 900.0
"""Wall-time budget of the calibration on 2 cores [s]."""
FINE = ForwardSettings(n_orientations=360, increment=1e-4, iso_increment=1e-4, stress_rtol=1e-5)
"""Reference forward model for the discretisation error."""
SYNTHETIC = ForwardSettings(n_orientations=72, increment=1e-4, iso_increment=1e-4, stress_rtol=1e-5)
"""Closed form at make_synthetic.py's DEM settings: the clean curves of the coverage study."""
COVERAGE_SEED = 20
"""Seed of realisation k: SeedSequence([20, k]); [20, 0] equals make_synthetic.py's seed 20 (zeros pad the
entropy), so realisation 0 draws the noise of the shipped files."""
NOISE = 0.02
"""Noise of the shipped data and of the coverage study, a fraction of each channel's largest abs value [-]."""


def discretisation_error(truth: dict[str, float], noise: float) -> None:
    params = {k: np.array([v]) for k, v in truth.items()}
    coarse = ForwardSettings(n_orientations=FORWARD.n_orientations, increment=FORWARD.increment,
                             iso_increment=FORWARD.iso_increment, stress_rtol=FORWARD.stress_rtol)
    print(f"forward model: {coarse.n_orientations} orientations, increment {coarse.increment:g}, iso "
          f"{coarse.iso_increment:g}, rtol {coarse.stress_rtol:g} against {FINE.n_orientations}, {FINE.increment:g}, "
          f"{FINE.iso_increment:g}, {FINE.stress_rtol:g} at the truth")
    for name in TESTS:
        test = read_test(DATA / name)
        start = time.perf_counter()
        a = simulate(test, params, coarse)
        t_coarse = time.perf_counter() - start
        b = simulate(test, params, FINE)
        sigma = bayes.channel_sigma(test, noise)
        errors = ", ".join(f"{c} {np.max(np.abs(a.channel(c) - b.channel(c))) / s:.3f} sigma" for c, s in sigma.items())
        print(f"  {name}: max abs(coarse - fine) = {errors}  (coarse run {t_coarse:.2f} s for one set)")


def replayed_noise(truth: dict[str, float]) -> None:
    """The shipped data split into the DEM curve and the noise by replaying make_synthetic.py's
    seeded draws: the closed form (``SYNTHETIC``) against that DEM curve (model error), and the
    noise draw itself (its rms and mean in sigma, which a correct likelihood expects near 1 and 0)."""
    import importlib.util  # noqa: PLC0415

    spec = importlib.util.spec_from_file_location("make_synthetic", DATA / "make_synthetic.py")
    synthetic = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(synthetic)
    rng = np.random.default_rng(synthetic.SEED)
    params = {k: np.array([v]) for k, v in truth.items()}
    print("shipped data = DEM curve + noise (make_synthetic.py's draws replayed):")
    for name in TESTS:
        test = read_test(DATA / name)
        model = simulate(test, params, SYNTHETIC)
        for c, observed in test.observed.items():
            z = rng.standard_normal(observed.size)
            scale = np.max(np.abs(observed))
            for _ in range(50):  # scale = max abs(clean), clean = observed - noise x scale x z
                scale = np.max(np.abs(observed - synthetic.NOISE * scale * z))
            sigma = synthetic.NOISE * scale
            dem = observed - sigma * z
            error = np.max(np.abs(dem - model.channel(c)[0])) / sigma
            print(f"  {name} {c}: closed form ({SYNTHETIC.n_orientations} orientations, increments "
                  f"{SYNTHETIC.increment:g}) - DEM: max {error:.1e} sigma; noise draw rms {np.sqrt(np.mean(z * z)):.2f}, "
                  f"mean {np.mean(z):+.2f} sigma (standard error of the mean {1 / np.sqrt(z.size):.2f}); "
                  f"likelihood sigma / drawn sigma {bayes.channel_sigma(test, NOISE)[c] / sigma:.3f}")


LOG = np.array([bayes.DEFAULT_BOUNDS[2][n][2] for n in PARAMETERS])
"""Parameters fitted as log10 (as sampled)."""


def to_coord(values: dict[str, float]) -> np.ndarray:
    """All ``PARAMETERS`` in sampled coordinates (log10 kn), shape (4,)."""
    return np.where(LOG, np.log10([values[n] for n in PARAMETERS]), [values[n] for n in PARAMETERS])


def gauss_newton(tests: list[Measurement], x0: np.ndarray, forward: ForwardSettings = FORWARD
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit of all ``PARAMETERS`` (sampled coordinates, from x0) of ``forward`` to ``tests``
    with the likelihood's sigma, and its Gauss-Newton standard deviations sqrt(diag (J^T J)^-1)."""
    from scipy.optimize import least_squares  # noqa: PLC0415

    def residuals(x: np.ndarray) -> np.ndarray:
        values = np.where(LOG, 10.0 ** x, x)
        params = {n: np.array([v]) for n, v in zip(PARAMETERS, values)}
        out = []
        for t in tests:
            model, sigma = simulate(t, params, forward), bayes.channel_sigma(t, NOISE)
            out += [(model.channel(c)[0] - v) / sigma[c] for c, v in t.observed.items()]
        return np.concatenate(out)

    fit = least_squares(residuals, x0, diff_step=1e-4, x_scale=np.where(LOG, 0.01, np.maximum(np.abs(x0) * 0.01, 0.01)))
    return fit.x, np.sqrt(np.diag(np.linalg.inv(fit.jac.T @ fit.jac)))


def parameter_bias(truth: dict[str, float]) -> None:
    """Bias of the calibration's forward model (``FORWARD``) in posterior standard deviations: its
    least-squares fit to the noise-free curves of ``SYNTHETIC`` at the truth, against the truth, the
    standard deviations from the Gauss-Newton covariance (J^T J)^-1 of that fit."""
    shipped = [read_test(DATA / name) for name in TESTS]
    truth_params = {k: np.array([v]) for k, v in truth.items()}
    tests = [replace(t, observed={c: simulate(t, truth_params, SYNTHETIC).channel(c)[0] for c in t.observed})
             for t in shipped]
    x0 = to_coord(truth)
    x, sd = gauss_newton(tests, x0)
    print("bias of the forward model (its fit to the noise-free curves at the truth), in posterior sd: "
          + ", ".join(f"{n} {b:+.2f}" for n, b in zip(PARAMETERS, (x - x0) / sd))
          + " (sd " + ", ".join(f"{n} {v:.3g}{' (log10)' if lg else ''}" for n, v, lg in zip(PARAMETERS, sd, LOG)) + ")")


def joint_region(truth: dict[str, float], run: dict, names: list[str]) -> None:
    """Whether the truth lies in the joint 95 % region: 2 (log L(MAP) - log L(truth)) against the
    chi-square quantile of as many degrees of freedom as parameters (Wilks)."""
    from scipy.stats import chi2  # noqa: PLC0415

    settings = run["config"]["forward"]
    forward = ForwardSettings(n_orientations=settings["n_orientations"], increment=settings["increment"],
                              iso_increment=settings["iso_increment"], stress_rtol=settings["stress_rtol"],
                              fixed=settings["fixed"])
    tests = [read_test(DATA / name) for name in TESTS]
    best = run["maximum_a_posteriori"]
    params = {n: np.array([truth[n], best[n]]) for n in names}
    curves = []
    for test in tests:
        c = simulate(test, params, forward)
        curves.append({k: c.channel(k) for k in ("q", "p", "eps_v")})
    ll = bayes.log_likelihood(tests, curves, run["forward_model"]["noise"])
    statistic, limit = 2.0 * (ll[1] - ll[0]), chi2.ppf(0.95, len(names))
    print(f"  joint 95 % region: 2 (log L(MAP) - log L(truth)) = {statistic:.2f}, chi2 95 % quantile "
          f"({len(names)} dof) {limit:.2f}: truth {'inside' if statistic <= limit else 'OUTSIDE'}")


def calibrate_in_process(tests: list[Measurement], prior: bayes.Prior, walkers: int, steps: int, burn: float,
                         seed: int, forward: ForwardSettings) -> tuple[dict, dict]:
    """The sampling of ``hmodel calibrate --start prior`` (same start, sampler, burn-in and stuck-walker
    rule) on ``tests``: its posterior summary (``bayes.summarise``) and sampler diagnostics."""
    import emcee  # noqa: PLC0415

    log_post = bayes.Posterior(tests, prior, forward, NOISE)
    sampler = emcee.EnsembleSampler(walkers, len(prior.names), log_post, vectorize=True)
    sampler.random_state = np.random.RandomState(seed).get_state()
    start, _ = prior_start(log_post, walkers, np.random.default_rng(seed))
    with np.errstate(divide="ignore", invalid="ignore"):  # sets too soft for p0 fail: counted in "failed"
        sampler.run_mcmc(start, steps)
    samples, _, _, stuck = retained_samples(sampler, burn)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = sampler.get_autocorr_time(tol=0)
    return bayes.summarise(samples, prior), {
        "stuck_walkers_left_out": stuck, "acceptance_fraction": float(np.mean(sampler.acceptance_fraction)),
        "autocorr_steps_max": float(np.nanmax(tau)), "fallbacks": log_post.n_fallback, "failed": log_post.n_failed}


def coverage_study(truth: dict[str, float], names: list[str], n: int, walkers: int, steps: int,
                   results: Path, laplace: bool, forward: ForwardSettings) -> None:
    """Empirical coverage of the 95 % intervals over ``n`` noise realisations (module docstring);
    ``laplace``: the Gauss-Newton interval (fit +- 1.96 sd) of each realisation instead of the chain."""
    from scipy.stats import binom  # noqa: PLC0415

    shipped = [read_test(DATA / name) for name in TESTS]
    clean = [simulate(t, {k: np.array([v]) for k, v in truth.items()}, SYNTHETIC) for t in shipped]
    prior = bayes.make_prior(names)
    realisations = []
    started = time.perf_counter()
    for k in range(n):
        rng = np.random.default_rng([COVERAGE_SEED, k])
        tests = []
        for t, c in zip(shipped, clean):
            observed = {}
            for ch in t.observed:
                v = c.channel(ch)[0]
                observed[ch] = v + NOISE * np.max(np.abs(v)) * rng.standard_normal(v.size)
            tests.append(replace(t, name=f"{k}:{t.name}", observed=observed))
        t0 = time.perf_counter()
        if laplace:
            x, sd = gauss_newton(tests, to_coord(truth), forward)
            entry = {"seed": k, "seconds": time.perf_counter() - t0, "posterior": {}}
            for i, name in enumerate(PARAMETERS):
                z = float((x[i] - to_coord(truth)[i]) / sd[i])
                entry["posterior"][name] = {"fit": float(np.where(LOG, 10.0 ** x, x)[i]), "z": z,
                                            "inside": abs(z) <= 1.96}
        else:
            summary, diagnostics = calibrate_in_process(tests, prior, walkers, steps, 0.5, k, forward)
            entry = {"seed": k, "seconds": time.perf_counter() - t0, **diagnostics, "posterior": {}}
            for name in names:
                s = summary[name]
                lo, hi = s["ci95"]
                entry["posterior"][name] = {"mean": s["mean"], "ci95": [lo, hi],
                                            "inside": bool(lo <= truth[name] <= hi)}
        realisations.append(entry)
        print(f"  realisation {k}: " + ", ".join(
            f"{name} {'in' if e['inside'] else 'OUT'}" for name, e in entry["posterior"].items())
            + f"  ({entry['seconds']:.0f} s" + ("" if laplace else f", stuck {entry['stuck_walkers_left_out']}, "
                                                f"tau {entry['autocorr_steps_max']:.0f} steps") + ")", flush=True)
    wall = time.perf_counter() - started
    lo_ok, hi_ok = binom.ppf(0.025, n, 0.95), binom.ppf(0.975, n, 0.95)
    coverage = {}
    method = "Gauss-Newton fit +- 1.96 sd" if laplace else f"{walkers} walkers x {steps} steps, burn-in 0.5"
    print(f"coverage of the 95 % intervals over {n} noise realisations ({method}), {wall:.0f} s; a correct 95 % "
          f"interval covers between {lo_ok:.0f} and {hi_ok:.0f} of {n} (binomial 95 % range):")
    for name in names:
        inside = sum(r["posterior"][name]["inside"] for r in realisations)
        coverage[name] = inside
        print(f"  {name}: truth inside {inside} of {n} ({100 * inside / n:.0f} %)")
    every = sum(all(e["inside"] for e in r["posterior"].values()) for r in realisations)
    print(f"  all parameters inside at once: {every} of {n}")
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps({
        "what": "empirical coverage of hmodel calibrate's 95 % intervals (benchmarks/bench_calibrate.py --coverage)",
        "truth": truth, "noise": NOISE, "clean_curves": asdict(SYNTHETIC), "forward_model": asdict(forward),
        "method": method, "realisations": n, "inside": coverage,
        "all_inside": every, "binomial_95_range": [float(lo_ok), float(hi_ok)], "wall_s": wall,
        "per_realisation": realisations}, indent=2, default=str) + "\n")
    print(f"  written to {results}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="phi_g,kn,kt_over_kn,alpha0")
    parser.add_argument("--walkers", type=int, default=32)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--out", type=Path, default=Path("runs/bench_calibrate"))
    parser.add_argument("--coverage", type=int, default=0, metavar="N",
                        help="measure the coverage over N noise realisations instead of the acceptance run")
    parser.add_argument("--laplace", action="store_true",
                        help="--coverage with the Gauss-Newton interval of each realisation instead of the chain")
    parser.add_argument("--increment", type=float, default=FORWARD.increment,
                        help="--coverage: forward increments (shear and isotropic) [-]")
    parser.add_argument("--stress-rtol", type=float, default=FORWARD.stress_rtol,
                        help="--coverage: forward stress tolerance [-]")
    parser.add_argument("--results", type=Path, default=Path(__file__).resolve().parent / "results"
                        / "calibration_coverage.json", help="JSON result of --coverage")
    args = parser.parse_args()
    truth = json.loads((DATA / "truth.json").read_text())
    if args.coverage:
        if sorted(args.params.split(",")) != sorted(PARAMETERS) or args.coverage < 1:
            parser.error(f"--coverage N (N >= 1) calibrates all of --params {','.join(PARAMETERS)}")
        forward = replace(FORWARD, increment=args.increment, iso_increment=args.increment, stress_rtol=args.stress_rtol)
        coverage_study(truth, args.params.split(","), args.coverage, args.walkers, args.steps, args.results,
                       args.laplace, forward)
        return 0
    discretisation_error(truth, NOISE)
    replayed_noise(truth)
    parameter_bias(truth)
    shutil.rmtree(args.out, ignore_errors=True)
    command = [sys.executable, "-m", "homogenization.calibrate", "-q", "--params", args.params, "--walkers",
               str(args.walkers), "--steps", str(args.steps), "--threads", "1", "--out", str(args.out)]
    for name in TESTS:
        command += ["--data", str(DATA / name)]
    names = args.params.split(",")
    fixed = {"phi_g": "--phi", "kn": "--kn", "alpha0": "--alpha0"}
    for name, flag in fixed.items():
        if name not in names:
            command += [flag, f"{truth[name]:g}"]
    if "kt_over_kn" not in names:
        command += ["--kt", f"{truth['kt_over_kn'] * truth['kn']:g}"]
    load = " / ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    posterior = json.loads((args.out / "posterior.json").read_text())
    run = json.loads((args.out / "run.json").read_text())
    print(f"calibration of {args.params} on {' + '.join(TESTS)}: {args.walkers} walkers x {args.steps} steps, "
          f"wall {wall:.0f} s (budget {BUDGET_S:.0f} s: {'PASS' if wall <= BUDGET_S else 'FAIL'}), CPU {cpu:.0f} s, "
          f"load average before {load}")
    ok = True
    for name in names:
        p, t = posterior[name], truth[name]
        kind, tol = TOLERANCE[name]
        error = p["mean"] - t if kind == "deg" else (p["mean"] - t) / t
        constrained = run["posterior"][name]["constrained"]
        inside = p["ci95"][0] <= t <= p["ci95"][1]
        within = abs(error) <= tol
        verdict = "PASS" if inside and (within or constrained is False) else "FAIL"  # None: undetermined
        ok &= verdict == "PASS"
        shown = f"{error:+.2f} deg" if kind == "deg" else f"{100 * error:+.2f} %"
        print(f"  {name}: truth {t:.4g}, mean {p['mean']:.4g}, ci95 [{p['ci95'][0]:.4g}, {p['ci95'][1]:.4g}], "
              f"error {shown} (allowed {tol:g}{' deg' if kind == 'deg' else ''}), truth in ci95: {inside}, "
              f"constrained: {constrained} -> {verdict}")
    joint_region(truth, run, names)
    for line in run["identifiability"]:
        print(f"  {line}")
    for which, values in run["misfit_rms_over_sigma"].items():
        print(f"  rms misfit / sigma, {which}: " + ", ".join(f"{k} {v:.2f}" for k, v in values.items()))
    s = run["sampler"]
    auto = s["autocorrelation"]
    print(f"  acceptance {s['acceptance_fraction']:.2f}, autocorrelation {auto['tau_steps']} steps, "
          f"effective samples {auto['effective_samples']} of {auto['samples']}, "
          f"forward evaluations {run['forward_model']['evaluations']}, fallbacks {run['forward_model']['fallbacks']}, "
          f"failed {run['forward_model']['failed']}")
    return 0 if ok and wall <= BUDGET_S else 1


if __name__ == "__main__":
    raise SystemExit(main())
