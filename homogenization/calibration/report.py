"""Outputs of a calibration: posterior samples and summary, figures, DEM confirmation, provenance.

Every file is written atomically (``warp_hcell.core.files.atomic_write``). Units: parameters in
the CLI flags' units (phi_g, alpha0 [deg], kn [N/m], kt_over_kn [-]); curves in N/m and [-].
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from homogenization.calibration import bayes, diagnostics
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import (CONTACT_LAW_KEY, CRITICAL_STATE_KEY, INTERLOCKING_KEY, ForwardSettings,
                                                contact_law_at, interlocking_at, rule_at, simulate)
from homogenization.output.figure_style import GRID, LABELS, apply_style, figure_legend
from homogenization.output.figures import save_figure
from warp_hcell.core.cli import quiet_warp
from warp_hcell.core.dimension import dimension
from warp_hcell.core.errors import UserError
from warp_hcell.core.files import atomic_write
from warp_hcell.core.provenance import provenance

BAND_DRAWS = 100
"""Posterior draws whose curves make the 95 % band of fits.png [-]."""
MAX_SAMPLES = 20000
"""Most retained samples written to posterior.h5 (the chain is thinned evenly beyond) [-]."""
SCALE = {"q": 1.0, "p": 1.0, "eps_v": 100.0}
"""Plot scale of each channel (eps_v in %)."""
LABELS_3D = {"q": r"$q = \sqrt{3 J_2}$ [Pa]", "p": r"$p = \mathrm{tr}\,\sigma / 3$ [Pa]",
             "eps_v": r"$\varepsilon_v = \varepsilon_{11} + \varepsilon_{22} + \varepsilon_{33}$"
                      " since the end of stage 1 [%]"}
"""Axis labels of the channels of a triaxial test (``LABELS`` holds the 2D ones)."""


OUTPUT_FILES = ("posterior.h5", "posterior.json", "corner.png", "fits.png", "run.json")
"""The files ``write_outputs`` writes beside the chain."""
STUCK_LOG_POSTERIOR = 20.0
"""A walker whose mean log posterior over the retained steps is this far below the median walker's
is stuck in a negligible mode (its density there is below exp(-20) of the bulk's) and left out of
the posterior; ``run.json`` counts them [-]."""


def retained_chain(sampler, burn: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Post-burn-in positions of the walkers that are not stuck (``STUCK_LOG_POSTERIOR``), shape
    (n_steps, n_kept, n_params) in sampled coordinates, their log posterior (n_steps, n_kept), the
    steps discarded and the walkers left out."""
    n_steps = sampler.backend.iteration
    discard = min(int(burn * n_steps), n_steps - 1)
    chain = sampler.get_chain(discard=discard)
    lp = sampler.get_log_prob(discard=discard)
    walker_mean = np.mean(lp, axis=0)
    keep = walker_mean >= np.median(walker_mean) - STUCK_LOG_POSTERIOR
    return chain[:, keep], lp[:, keep], discard, int(np.count_nonzero(~keep))


def retained_samples(sampler, burn: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """``retained_chain`` flattened to samples (n, n_params) and their log posterior (n,), thinned
    evenly to at most ``MAX_SAMPLES``; the steps discarded and the walkers left out."""
    chain, lp, discard, stuck = retained_chain(sampler, burn)
    chain, lp = chain.reshape(-1, chain.shape[2]), lp.reshape(-1)
    thin = max(1, math.ceil(chain.shape[0] / MAX_SAMPLES))
    return chain[::thin], lp[::thin], discard, stuck


def write_json(path: Path, data: Any) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")


def write_samples(path: Path, samples: np.ndarray, lp: np.ndarray, prior: bayes.Prior, attrs: Mapping[str, str]) -> None:
    """posterior.h5: /samples/<name> in CLI units and /log_posterior, shape (n,); provenance as attributes."""
    import h5py  # noqa: PLC0415

    values = prior.to_values(samples)
    with atomic_write(path) as tmp:
        with h5py.File(tmp, "w") as fh:
            group = fh.create_group("samples")
            for i, name in enumerate(prior.names):
                ds = group.create_dataset(name, data=values[:, i])
                ds.attrs["units"] = bayes.UNITS[name]
            fh.create_dataset("log_posterior", data=lp)
            for key, value in attrs.items():
                fh.attrs[key] = value


class _BareContours(logging.Filter):
    """Drops and counts the root logger's records of ``corner``'s panels without contours."""

    MESSAGE = "Too few points to create valid contours"

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if record.getMessage().startswith(self.MESSAGE):
            self.count += 1
            return False
        return True


def corner_figure(samples: np.ndarray, prior: bayes.Prior) -> tuple[Figure, int]:
    """Corner plot of the posterior in CLI units (log10 kn where its prior is log-uniform), and the number of
    its 2D panels drawn without contours (too few distinct samples, as from a short chain: ``corner`` logs
    one warning per panel, which are counted here instead of printed)."""
    import corner  # noqa: PLC0415

    labels = [f"log10 {n} [{bayes.UNITS[n]}]" if lg else f"{n} [{bayes.UNITS[n]}]"
              for n, lg in zip(prior.names, prior.log)]
    k = len(prior.names)
    fig = Figure(figsize=(2.2 * k + 1, 2.2 * k + 1))
    root, bare = logging.getLogger(), _BareContours()
    idle = logging.lastResort if not root.handlers else None  # as Python prints, without logging.warning()'s basicConfig
    root.addFilter(bare)
    if idle is not None:
        root.addHandler(idle)
    try:
        corner.corner(samples, labels=labels, quantiles=[0.025, 0.5, 0.975], show_titles=True, fig=fig)
    finally:
        root.removeFilter(bare)
        if idle is not None:
            root.removeHandler(idle)
    return fig, bare.count


def fit_figure(tests: Sequence[Measurement], log_post: bayes.Posterior, samples: np.ndarray,
               mean_curves: Sequence[Mapping[str, np.ndarray]], confirm: Sequence[Mapping[str, np.ndarray]] | None,
               rng: np.random.Generator) -> Figure:
    """Measured points (+- sigma), posterior median and 95 % band of the forward model, DEM at the mean."""
    draws = samples[rng.choice(samples.shape[0], size=min(BAND_DRAWS, samples.shape[0]), replace=False)]
    band = log_post.curves(log_post.prior.to_values(draws))
    n_cols = max(len(t.observed) for t in tests)
    fig = Figure(figsize=(4.5 * n_cols, 3.6 * len(tests) + 0.8), layout="constrained")
    axes = fig.subplots(len(tests), n_cols, squeeze=False)
    handles = []
    for row, (test, curves) in enumerate(zip(tests, band)):
        sigma = bayes.channel_sigma(test, log_post.noise)
        x = 100.0 * test.eps1
        for col, (c, observed) in enumerate(test.observed.items()):
            ax = axes[row, col]
            s = SCALE[c]
            lo, med, hi = np.nanquantile(curves[c], [0.025, 0.5, 0.975], axis=0)
            h_band = ax.fill_between(x, s * lo, s * hi, color="C0", alpha=0.3, label="posterior 95 % band")
            (h_med,) = ax.plot(x, s * med, color="C0", label=f"posterior median ({log_post.settings.backend})")
            h_data = ax.errorbar(x, s * observed, yerr=s * sigma[c], fmt="o", ms=3, color="k", label="data (+- sigma)")
            handles_row = [h_data, h_band, h_med]
            if confirm is not None:
                (h_dem,) = ax.plot(x, s * confirm[row][c], "--", color="C3", label="DEM at the posterior mean")
                handles_row.append(h_dem)
            ax.set(xlabel=LABELS["eps1"], ylabel={2: LABELS, 3: LABELS_3D}[test.dim][c],
                   title=f"{test.name} ({test.kind}, p0 = {test.p0:g} {dimension(test.dim).stress_unit})")
            ax.grid(**GRID)
            handles = handles or handles_row
        for col in range(len(test.observed), n_cols):
            axes[row, col].set_visible(False)
    figure_legend(fig, handles)
    return apply_style(fig)


def misfit(tests: Sequence[Measurement], curves: Sequence[Mapping[str, np.ndarray]], noise: float) -> dict[str, float]:
    """Root-mean-square residual over sigma of each test and channel ("test:channel" -> value)."""
    out = {}
    for test, model in zip(tests, curves):
        for c, sigma in bayes.channel_sigma(test, noise).items():
            r = (np.asarray(model[c]).reshape(-1) - test.observed[c]) / sigma
            out[f"{test.name}:{c}"] = float(np.sqrt(np.mean(r * r)))
    return out


def confirm_with_dem(tests: Sequence[Measurement], log_post: bayes.Posterior, mean: np.ndarray,
                     args: argparse.Namespace) -> list[dict[str, np.ndarray]]:
    """Curves of the DEM backend at the posterior mean (one run per test)."""
    if not args.verbose:
        quiet_warp(args.device)
    options = {"device": args.device, **({"threads": args.threads} if args.threads is not None else {})}
    settings = replace(log_post.settings, backend="dem", n_orientations=args.confirm_orientations,
                       backend_options=options)
    params = {name: mean[i:i + 1] for i, name in enumerate(log_post.prior.names)}
    out = []
    for test in tests:
        c = simulate(test, params, settings)
        out.append({name: c.channel(name)[0] for name in test.observed})
    return out


def posterior_json(summary: Mapping[str, Mapping[str, Any]], names: Sequence[str],
                   settings: ForwardSettings) -> dict[str, Any]:
    """posterior.json: mean, median and ci95 of each calibrated parameter; with a law other than the
    linear one (the default, not named), ``contact_law``: that law at the posterior mean (``to_dict``); with
    a critical-state rule, ``critical_state``: the rule at the posterior mean (``forward.rule_at``); with the
    interlocking friction, ``interlocking``: it at the posterior mean (``forward.interlocking_at``)."""
    data: dict[str, Any] = {n: {k: summary[n][k] for k in ("mean", "median", "ci95")} for n in names}
    if settings.law != ForwardSettings.law:
        at_mean = {name: np.array([summary[name]["mean"] if name in summary else settings.fixed[name]])
                   for name in settings.parameters}
        data[CONTACT_LAW_KEY] = contact_law_at(at_mean, 0, settings.law).to_dict()
    if settings.critical_state is not None:
        data[CRITICAL_STATE_KEY] = asdict(rule_at({n: summary[n]["mean"] for n in names}, settings))
    if settings.interlocking is not None:
        data[INTERLOCKING_KEY] = asdict(interlocking_at({n: summary[n]["mean"] for n in names}, settings))
    return data


def resolution_at_optimum(log_post: bayes.Posterior, record: Mapping[str, Any], x: np.ndarray) -> dict[str, Any]:
    """run.json's ``forward_model.resolution``: ``record`` (``cli.calibrate.resolved_start``) and the check at
    the optimum ``x`` (sampled coordinates) as ``optimum``: against the reference where a correction is
    applied, else against the refined models; none with --resolution off."""
    from homogenization.calibration import resolution  # noqa: PLC0415

    out = {k: v for k, v in record.items() if k != "correction"}
    if record.get("mode", "off") == "off":
        return out
    if record.get("correction") is not None:
        reference = replace(log_post.settings, **record["reference"])
        optimum = resolution.check(log_post, x, "optimum", against=reference)
        out["correction_max_abs_over_sigma"] = {
            f"{t.name}:{c}": float(np.max(np.abs(v)) / sigma) for t, corr in zip(log_post.tests, log_post.correction)
            for c, sigma in bayes.channel_sigma(t, log_post.noise).items() for v in [corr[c]]}
    else:
        optimum = resolution.check(log_post, x, "optimum")
    out["optimum"] = optimum.to_dict()
    out["optimum_line"] = optimum.line()
    return out


def write_outputs(out: Path, sampler, log_post: bayes.Posterior, args: argparse.Namespace, seconds: float,
                  config: Mapping[str, Any], start: Mapping[str, Any] | None = None,
                  resolution_record: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write posterior.h5, posterior.json, corner.png, fits.png and run.json; returns run.json's content.
    ``resolution_record``: the forward model's resolution checks at the start (``cli.calibrate.resolved_start``).

    Raises:
        UserError: every retained sample has a log posterior of -inf (nothing is written)."""
    from homogenization.calibration import resolution  # noqa: PLC0415

    prior, tests = log_post.prior, log_post.tests
    counts = forward_counts(log_post.counts())  # the sampler's runs (the start's are in ``start``), not the ones below
    samples, lp, discard, stuck = retained_samples(sampler, args.burn)
    if not np.isfinite(lp).any():
        raise UserError(f"no posterior: the forward model failed (a non-finite curve) or the prior refused every "
                        f"walker at every retained step ({int(lp.size)} samples); start elsewhere (--start-point) or "
                        f"narrow the prior (--prior)")
    autocorrelation = diagnostics.chain_diagnostics(retained_chain(sampler, args.burn)[0], prior.names)
    summary = bayes.summarise(samples, prior, short=autocorrelation["short"])
    corr = bayes.correlations(samples, prior)
    note = bayes.identifiability_note(summary, corr)
    mean = np.array([summary[n]["mean"] for n in prior.names])
    best = prior.to_values(samples[np.argmax(lp)])
    both = log_post.curves(np.stack([mean, best]))
    mean_curves, best_curves = ([{c: v[k] for c, v in curves.items()} for curves in both] for k in (0, 1))
    confirm = confirm_with_dem(tests, log_post, mean, args) if args.confirm == "dem" else None
    x_best = samples[np.argmax(lp)]
    resolution_run = resolution_at_optimum(log_post, resolution_record or {"mode": "off"}, x_best)
    fit = resolution.misfit(log_post, x_best, args.noise)
    autocorrelation["converged"] = not autocorrelation["short"]
    autocorrelation["steps_needed"] = diagnostics.steps_needed(autocorrelation, int(sampler.backend.iteration),
                                                               args.burn)
    record = provenance()
    run = {
        "data_dimensions": sorted({t.dim for t in tests}),
        "tests": [{"name": t.name, "kind": t.kind, "p0": t.p0, "dim": t.dim} for t in tests],
        "identifiability": note,
        "correlations": corr,
        "sampler": {
            "library": "emcee", "walkers": args.walkers, "steps": int(sampler.backend.iteration),
            "burn": args.burn, "discarded": discard, "retained_samples": int(samples.shape[0]), "stuck_walkers_left_out": stuck,
            "acceptance_fraction": float(np.mean(sampler.acceptance_fraction)),
            "autocorrelation": autocorrelation, "seconds_this_run": seconds,
        },
        "start": dict(start) if start is not None else None,
        "forward_model": {
            "settings": config["forward"], "noise": args.noise,
            **{k: v for k, v in counts.items() if k != "infeasible_sets" or log_post.spread_cut},
            "model_error": getattr(args, "model_error", 0.0),
            "likelihood_sigma_fraction": log_post.noise, "resolution": resolution_run,
            **_ann_model(config["forward"]["backend"]),
        },
        "maximum_a_posteriori": {n: float(v) for n, v in zip(prior.names, best)},
        "misfit_rms_over_sigma": {"forward_at_mean": misfit(tests, mean_curves, log_post.noise),
                                  "forward_at_maximum_a_posteriori": misfit(tests, best_curves, log_post.noise),
                                  **({"dem_at_mean": misfit(tests, confirm, log_post.noise)} if confirm else {})},
        "misfit_against_noise": {**fit.to_dict(), "warning": fit.warning(args.noise)},
        "config": config,
        "provenance": record,
    }
    write_samples(out / "posterior.h5", samples, lp, prior, record)
    write_json(out / "posterior.json", posterior_json(summary, prior.names, log_post.settings))
    corner, bare_panels = corner_figure(samples, prior)
    save_figure(corner, out / "corner.png")
    run["sampler"]["corner_panels_without_contours"] = bare_panels
    save_figure(fit_figure(tests, log_post, samples, mean_curves, confirm, np.random.default_rng(args.seed)),
                out / "fits.png")
    write_json(out / "run.json", {"posterior": summary, **run})
    return {"posterior": summary, **run}


def forward_counts(counts: Mapping[str, int], start: bool = False) -> dict[str, int]:
    """run.json's names of the counters ``bayes.Posterior.counts``: ``evaluations`` the sets that the sampler's log
    posterior ran (``start``: every set run, for the start's fits and checks; failed and infeasible sets are the start
    record's own there)."""
    out = {"evaluations": counts["n_sets" if start else "n_calls"], "fallbacks": counts["n_fallback"],
           "jumps": counts["n_jump"], "interlocking_clips": counts["n_clip"], "renewal_clips": counts["n_renewal_clip"],
           "floating_point_errors": counts["n_float_errors"]}
    return out if start else {**out, "failed": counts["n_failed"], "infeasible_sets": counts["n_infeasible"]}


def _ann_model(backend: str) -> dict[str, Any]:
    """``{"ann_model": ...}``, the installed model's record (sha256, certificate worst, certified,
    the problem; ``homogenization.ann.policy.model_record``), for the ann backend; else {}."""
    if backend != "ann":
        return {}
    from homogenization.ann.policy import model_record  # noqa: PLC0415 (torch: ann only)

    return {"ann_model": model_record(None)}


def start_line(start: Mapping[str, Any]) -> str:
    """One status line of the walkers' start (``homogenization.calibration.start``)."""
    if start["method"] == "prior":
        return f"start: the best of {start['prior_draws']} prior draws"
    optimum = ", ".join(f"{k} {v:.4g}" for k, v in start["optimum"].items())
    if "refit_from" in start:
        fits = start["least_squares_starts"]
        how = ("one fit from the previous optimum" if fits == 1 else
               f"the best of {fits} fits from scaled start points (chi-square "
               + ", ".join(f"{fit['chi_square']:.4g}" for fit in start["fits"]) + ")")
        return (f"start: least-squares optimum {optimum} (chi-square {start['chi_square']:.4g} over {start['residuals']} "
                f"residuals; {how}, {start['evaluations']} forward evaluations); walkers drawn around it from its "
                f"Laplace approximation")
    return (f"start: least-squares optimum {optimum} (chi-square {start['chi_square']:.4g} over {start['residuals']} "
            f"residuals; best of {start['least_squares_starts'] + start.get('more_fits', 0)} fits from {start['prior_draws']} "
            f"prior draws{', ' + str(start['more_fits']) + ' of them because the first ones missed the data far above the noise' if start.get('more_fits') else ''}, "
            f"{start['evaluations']} forward evaluations in {start['forward_batches']} batches, "
            f"{start['failed_sets']} failed sets); walkers drawn around it from its Laplace approximation "
            f"(sd at most {start['ball_fraction_of_prior_width']:g} x the prior width)")


def summary_lines(result: Mapping[str, Any]) -> list[str]:
    """Status lines: one per parameter, then the identifiability note and the misfits."""
    lines = [start_line(result["start"])] if result.get("start") else []
    res = result.get("forward_model", {}).get("resolution", {})
    lines += [f"after the discretisation correction, {start_line(again)}" for again in res.get("starts_after_correction", [])]
    if res.get("mode", "off") != "off":
        lines.append(f"forward-model resolution: {res.get('refinements', 0)} refinements to the reference "
                     f"{res.get('reference')}, {'a correction applied' if res.get('corrected_at') else 'no correction'} "
                     f"({res.get('restarts', 0)} starts found again)")
        if "optimum_line" in res:
            lines.append(res["optimum_line"])
    for name, s in result["posterior"].items():
        lo, hi = s["ci95"]
        lines.append(f"{name}: mean {s['mean']:.4g}, median {s['median']:.4g}, 95 % [{lo:.4g}, {hi:.4g}] {s['unit']}")
    lines += result["identifiability"]
    for which, values in result["misfit_rms_over_sigma"].items():
        lines.append(f"rms misfit / sigma, {which}: " + ", ".join(f"{k} {v:.2f}" for k, v in values.items()))
    fit = result.get("misfit_against_noise")
    if fit is not None:
        lines.append(f"misfit at the optimum: reduced chi-square {fit['reduced_chi_square']:.2f} over "
                     f"{fit['residuals']} residuals ({'FAR ABOVE' if fit['far_above_noise'] else 'within'} the noise; "
                     f"limit {fit['limit']:.2f})")
    sampler, forward = result["sampler"], result["forward_model"]
    start = (result.get("start") or {}).get("forward_counts")  # none in a chain started before the start's were kept
    auto = sampler.get("autocorrelation")  # absent from a result made without a chain
    if auto is not None and "converged" in auto:
        lines.append(f"chains converged: {'yes' if auto['converged'] else 'NO'} ({_number(auto['steps_per_tau'], '.1f')} "
                     f"autocorrelation times retained, {auto['rule_steps_per_tau']:g} needed"
                     + ("" if auto["converged"] else f"; at least --steps {auto['steps_needed']} in all: tau's estimate "
                                                         f"grows with the chain, so rerun with it (the chain resumes) and "
                                                         f"read this line again") + ")")
    if auto is not None:
        lines.append("autocorrelation time [steps] / effective samples: " + ", ".join(
            f"{n} {_number(t, '.1f')} / {_number(auto['effective_samples'][n], '.0f')}"
            for n, t in auto["tau_steps"].items())
            + f" (of {auto['samples']} samples, {auto['steps_retained']} retained steps = "
            f"{_number(auto['steps_per_tau'], '.1f')} x the largest tau)")
    lines.append(f"sampler: {sampler['steps']} steps x {sampler['walkers']} walkers, acceptance "
                 f"{sampler['acceptance_fraction']:.2f}, stuck walkers left out {sampler['stuck_walkers_left_out']}, "
                 f"forward fallbacks {forward['fallbacks']} in {forward['evaluations']} evaluations"
                 + (f" (the start's: {start['fallbacks']} in {start['evaluations']})" if start else "") +
                 f", jumps {forward.get('jumps', 0)}, clips: interlocking "
                 f"{forward.get('interlocking_clips', 0)}, renewal {forward.get('renewal_clips', 0)}, "
                 f"failed sets {forward['failed']}, "
                 + (f"infeasible sets {forward['infeasible_sets']}, " if "infeasible_sets" in forward else "") +
                 f"floating-point errors {forward.get('floating_point_errors', 0)} (overflow or NaN of diverging sets, "
                 f"not printed)")
    bare = sampler.get("corner_panels_without_contours", 0)
    if bare:
        k = len(result["posterior"])
        lines.append(f"corner.png: {bare} of {k * (k - 1) // 2} panels without contours (too few distinct samples: a "
                     f"short chain)")
    stuck = sampler["stuck_walkers_left_out"]
    if stuck:
        lines.append(f"{stuck} of {sampler['walkers']} walkers stayed where the posterior is below exp(-"
                     f"{STUCK_LOG_POSTERIOR:g}) of the other walkers' and are left out of it; if that is many, rerun "
                     f"with a --prior narrowed around the posterior above or with more --walkers")
    return lines


def warnings(result: Mapping[str, Any]) -> list[str]:
    """Every warning line of a calibration: the chain too short, the misfit far above the noise, the
    forward model not resolved at the optimum."""
    lines = [chain_warning(result)]
    lines.append(result.get("misfit_against_noise", {}).get("warning"))
    optimum = result.get("forward_model", {}).get("resolution", {}).get("optimum")
    if optimum is not None and not optimum["passed"]:
        lines.append(f"warning: at the optimum the forward model's discretisation error is not well below the noise "
                     f"(estimated {max(optimum['error_rms_over_sigma'].values()):.2f} sigma rms, parameter shift "
                     f"{max(optimum['error_shift_over_sd'].values()):.2f} sd): the intervals may be biased; rerun with a finer --increment and --orientations")
    return [line for line in lines if line]


def chain_warning(result: Mapping[str, Any]) -> str | None:
    """The one warning line of a chain too short for its autocorrelation time (``diagnostics.warning_line``)."""
    sampler = result["sampler"]
    if "autocorrelation" not in sampler:
        return None
    return diagnostics.warning_line(sampler["autocorrelation"], sampler["steps"], sampler["burn"])


def _number(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec``, or "n/a" for None (a parameter that never moved)."""
    return "n/a" if value is None else format(value, spec)
