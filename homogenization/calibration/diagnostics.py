"""The sampler's own diagnostics: integrated autocorrelation time and effective sample size.

For each parameter, emcee's integrated autocorrelation time tau [steps] of the retained part of
the chain (after burn-in, stuck walkers left out), estimated with ``emcee.autocorr.integrated_time``
at ``tol=0`` (an estimate is returned however short the chain; its reliability is what
``STEPS_PER_TAU`` judges), over the walkers that moved in that parameter (a walker whose every
proposal was rejected has no autocorrelation; they are counted). The effective number of independent samples is

    ESS = n_walkers_kept * n_steps_retained / tau    [-]

at most the number of retained samples (an estimate tau < 1, which a short or anticorrelated
chain can give, is counted in ``ess_capped`` and ESS is set to the number of samples). emcee's
rule of thumb trusts tau, and so the posterior's quantiles, only on chains longer than
``STEPS_PER_TAU`` x tau: a shorter one is flagged ``short`` (one warning line with advice).
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

STEPS_PER_TAU = 50.0
"""Retained steps per autocorrelation time below which the chain counts as too short to trust
tau (emcee's rule of thumb) [-]."""


def chain_diagnostics(chain: np.ndarray, names: Sequence[str]) -> dict[str, Any]:
    """Autocorrelation times and effective sample sizes of a retained chain.

    Args:
        chain: post-burn-in positions of the walkers kept, shape (n_steps, n_walkers, n_params),
            sampled coordinates (log10 kn for a log-uniform prior).
        names: parameter names, length n_params.

    Returns:
        run.json's ``sampler.autocorrelation``: ``tau_steps`` and ``effective_samples`` per name
        (None where tau is not finite: a parameter that never moved), ``samples`` (n_steps x
        n_walkers), ``steps_retained``, ``steps_per_tau`` (n_steps / the largest tau),
        ``ess_capped`` (names whose tau < 1 was raised to 1), ``walkers_that_never_moved`` per
        name (left out of tau's estimate, their samples kept in ESS's count), ``short`` (steps_per_tau below
        ``STEPS_PER_TAU`` or a tau that is not finite), ``rule_steps_per_tau``.
    """
    import emcee  # noqa: PLC0415 (only where a calibration ran)

    n_steps, n_walkers, _ = chain.shape
    n_samples = n_steps * n_walkers
    tau_steps: dict[str, float | None] = {}
    ess: dict[str, float | None] = {}
    still: dict[str, int] = {}
    capped = []
    for d, name in enumerate(names):
        moved = np.ptp(chain[:, :, d], axis=0) > 0.0  # a walker that never moved has no autocorrelation
        still[name] = int(np.count_nonzero(~moved))
        t = float(emcee.autocorr.integrated_time(chain[:, moved, d:d + 1], tol=0)[0]) if moved.any() and n_steps > 1 \
            else math.nan
        if not math.isfinite(t):
            tau_steps[name], ess[name] = None, None
            continue
        tau_steps[name] = t
        if t < 1.0:
            capped.append(name)
        ess[name] = n_samples / max(t, 1.0)
    finite = [t for t in tau_steps.values() if t is not None]
    worst = max(finite) if finite else math.nan
    steps_per_tau = n_steps / max(worst, 1.0) if finite else None
    short = steps_per_tau is None or len(finite) < len(names) or steps_per_tau < STEPS_PER_TAU
    return {"tau_steps": tau_steps, "effective_samples": ess, "samples": n_samples, "steps_retained": n_steps,
            "steps_per_tau": steps_per_tau, "rule_steps_per_tau": STEPS_PER_TAU, "ess_capped": capped,
            "walkers_that_never_moved": still,
            "short": bool(short)}


def steps_needed(diag: dict[str, Any], steps_total: int, burn: float) -> int | None:
    """Total steps (burn-in included) for ``STEPS_PER_TAU`` autocorrelation times of ``diag``'s largest tau,
    at least ``steps_total``; None where no tau is finite. A lower bound: tau estimated on a chain shorter
    than ``STEPS_PER_TAU`` x tau is biased low, and grows as the chain does."""
    finite = [t for t in diag["tau_steps"].values() if t is not None]
    if not finite:
        return None
    need = math.ceil(diag["rule_steps_per_tau"] * max(max(finite), 1.0) / max(1.0 - burn, 1e-9))
    return max(need, steps_total)


def warning_line(diag: dict[str, Any], steps_total: int, burn: float) -> str | None:
    """One warning line with advice where ``diag`` (``chain_diagnostics``) is ``short``; else None."""
    if not diag["short"]:
        return None
    finite = [t for t in diag["tau_steps"].values() if t is not None]
    if not finite:
        return (f"warning: the chain's autocorrelation time cannot be estimated ({diag['steps_retained']} retained "
                f"steps; a parameter never moved): its intervals are not to be trusted; run more --steps")
    worst = max(finite)
    need = math.ceil(diag["rule_steps_per_tau"] * max(worst, 1.0) / max(1.0 - burn, 1e-9))
    tau_text = f"largest tau {worst:.1f} steps" if worst >= 1.0 else "tau below one step: too few steps to estimate it"
    return (f"warning: the chain is short: {diag['steps_retained']} retained steps = {diag['steps_per_tau']:.1f} "
            f"autocorrelation times ({tau_text}), under the {diag['rule_steps_per_tau']:g} that "
            f"make tau and the 95 % intervals trustworthy; rerun the same command with --steps {max(need, steps_total + 1)} "
            f"or more (it resumes the chain); tau itself grows as the chain does")
