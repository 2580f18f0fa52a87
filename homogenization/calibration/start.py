"""Where the walkers of a calibration start: the best prior draws, or a ball around a least-squares optimum.

``prior``: the ``n_walkers`` best of ``PRIOR_OVERSAMPLE`` x n_walkers prior draws (one batch of the
forward model). Walkers that start in a secondary mode of the posterior stay there (emcee's stretch
move does not leave it): they are left out at the end as stuck walkers.

``map``: a deterministic (seeded) multi-start least-squares fit first. ``MAP_DRAWS`` prior draws
(one batch), the ``MAP_STARTS`` best of them as starting points of ``scipy.optimize.least_squares``
('trf', bounded by the prior) on the residuals the likelihood uses (``bayes.residuals``: (model -
observed) / sigma of every channel and point, so that least squares maximises the posterior inside
the uniform prior), in the sampler's coordinates (log10 kn where its prior is log-uniform), each
with at most ``MAP_MAX_EVALUATIONS`` residual evaluations. The Jacobian is a forward difference of
step ``MAP_STEP`` x the prior's width per parameter, its n_params perturbed sets run as one batch.
The walkers start around the best optimum, drawn from the posterior's
Laplace approximation there (covariance (J^T J)^-1 of the last Jacobian; along a direction the
data do not constrain its sd is capped at ``MAP_BALL`` x the prior's width), clipped into the prior. A parameter set whose forward model fails (NaN) gets the residual
``FAILED_RESIDUAL`` on every point, counted. The Jacobian reuses the residuals at x that the fit has
just computed (least_squares asks for the Jacobian only at a point it has evaluated). Where
alpha0_spread is calibrated, a set outside the prior's cut (alpha0 - alpha0_spread below the
ten-sphere cell's smallest opening; ``bayes.Posterior.feasible``) gets ``FAILED_RESIDUAL`` without a
run, counted in ``infeasible``, and a Jacobian step that would leave the cut goes the other way;
the walkers' ball is drawn again where it leaves the cut. Where the best of the ``MAP_STARTS`` fits
misses the data far above their noise (``MAP_MISFIT_QUANTILE``; e.g. a secondary mode, which a
narrow, curved valley of the posterior can hold), the start also fits from the other draws, best
first, until a fit is within that quantile (recorded as ``more_fits``), and keeps the best fit.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from homogenization.calibration import bayes

PRIOR_OVERSAMPLE = 8
"""Prior draws per walker of the ``prior`` start [-]."""
MAP_DRAWS = 16
"""Prior draws from which the ``map`` start picks its starting points [-]."""
MAP_STARTS = 3
"""Least-squares fits of the ``map`` start, from its best prior draws [-]."""
MAP_MAX_EVALUATIONS = 40
"""Residual evaluations (scipy's max_nfev; the Jacobian's are not counted by it) per least-squares fit [-]."""
MAP_STEP = 1e-3
"""Forward-difference step of the Jacobian, as a fraction of the prior's width in sampled coordinates [-]."""
MAP_BALL = 1e-2
"""Largest sd of the walkers' start around the optimum, as a fraction of the prior's width in sampled
coordinates [-]."""
MAP_MISFIT_QUANTILE = 0.999
"""Where the best fit's chi-square is above this quantile of chi-square (residuals - parameters degrees of
freedom), far above the noise, the ``map`` start also fits from its other ``MAP_DRAWS`` draws until a fit is
below it [-]."""
FAILED_RESIDUAL = 1e3
"""Residual [sigma] given to every point of a parameter set whose forward model failed [-]."""


class Residuals:
    """Batched residual vectors of parameter sets in sampled coordinates, counting what it runs.

    ``evaluations``: parameter sets run; ``batches``: forward-model calls; ``failed``: sets whose
    forward model failed (their residuals are ``FAILED_RESIDUAL``).
    """

    def __init__(self, log_post: bayes.Posterior) -> None:
        self.log_post = log_post
        self.evaluations = 0
        self.batches = 0
        self.failed = 0
        self.infeasible = 0

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Residuals of sets x, shape (n, n_params) -> (n, n_residuals)."""
        x = np.atleast_2d(x)
        ok = self.log_post.feasible(x)
        if not ok.all():
            self.infeasible += int(np.count_nonzero(~ok))
            r = np.full((x.shape[0], self.n_residuals), FAILED_RESIDUAL)
            if ok.any():
                r[ok] = self(x[ok])
            return r
        curves = self.log_post.curves(self.log_post.prior.to_values(x))
        r = bayes.residuals(self.log_post.tests, curves, self.log_post.noise)
        bad = ~np.all(np.isfinite(r), axis=1)
        self.evaluations += x.shape[0]
        self.batches += 1
        self.failed += int(np.count_nonzero(bad))
        r[bad] = FAILED_RESIDUAL
        return r

    @property
    def n_residuals(self) -> int:
        """Residuals per set: every measured point of every channel of every test."""
        return sum(v.size for t in self.log_post.tests for v in t.observed.values())


def laplace_draws(jac: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """n draws of the Laplace approximation N(0, (J^T J)^-1) of the posterior at a least-squares optimum,
    its sd along every eigen-direction capped at ``MAP_BALL``, shape (n, n_params).

    Args:
        jac: Jacobian of the residuals in coordinates scaled by the prior's width, shape (n_residuals, n_params).
    """
    curvature, directions = np.linalg.eigh(jac.T @ jac)
    sd = np.minimum(1.0 / np.sqrt(np.maximum(curvature, 1e-300)), MAP_BALL)
    return (rng.standard_normal((n, sd.size)) * sd) @ directions.T


def prior_start(log_post: bayes.Posterior, n_walkers: int, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The ``prior`` start (module docstring): positions (n_walkers, n_params) and its record."""
    start = bayes.initial_walkers(log_post, log_post.prior, n_walkers, rng, oversample=PRIOR_OVERSAMPLE)
    return start, {"method": "prior", "prior_draws": PRIOR_OVERSAMPLE * n_walkers}


def least_squares_fit(res: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                      feasible: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[float, Any]:
    """One bounded least-squares fit of ``map_start`` from ``x0`` (sampled coordinates) inside [lo, hi]: its
    chi-square (sum of squared residuals) and scipy's result. ``res`` maps parameter sets (k, n_params) to
    residual vectors (k, m) in one batch; the Jacobian's forward differences step inwards at ``hi`` and
    where ``feasible`` (sets (k, n_params) -> (k,) bool, e.g. the prior's cut) refuses the step."""
    from scipy.optimize import least_squares  # noqa: PLC0415 (only when a calibration starts)

    width = hi - lo
    last: dict[str, np.ndarray] = {}

    def fun(x: np.ndarray) -> np.ndarray:
        last["x"], last["f"] = np.array(x, dtype=np.float64), res(np.atleast_2d(x))[0]
        return last["f"]

    def jac(x: np.ndarray) -> np.ndarray:
        step = MAP_STEP * width
        step = np.where(x + step > hi, -step, step)  # stay inside the prior at its upper bound
        if feasible is not None:
            step = np.where(feasible(x + np.diag(step)), step, -step)  # and inside its cut (alpha0_spread)
        f0 = last["f"] if "x" in last and np.array_equal(last["x"], x) else res(np.atleast_2d(x))[0]
        return ((res(x + np.diag(step)) - f0) / step[:, None]).T

    fit = least_squares(fun, x0, jac=jac, bounds=(lo, hi), x_scale=width, method="trf", max_nfev=MAP_MAX_EVALUATIONS)
    return float(2.0 * fit.cost), fit


def far_above_noise(n_residuals: int, n_params: int) -> float:
    """The chi-square above which a fit misses ``n_residuals`` residuals far above their noise
    (``MAP_MISFIT_QUANTILE`` of chi-square with n_residuals - n_params degrees of freedom)."""
    from scipy.stats import chi2  # noqa: PLC0415

    return float(chi2.ppf(MAP_MISFIT_QUANTILE, max(n_residuals - n_params, 1)))


def map_start(log_post: bayes.Posterior, n_walkers: int, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The ``map`` start (module docstring): positions (n_walkers, n_params) and its record (the
    optimum in CLI units, its chi-square sum of squared residuals, every fit's, the evaluations)."""
    prior = log_post.prior
    lo, hi = prior.lo_coord, prior.hi_coord
    width = hi - lo
    res = Residuals(log_post)
    draws = prior.sample(rng, MAP_DRAWS)
    cost = np.sum(res(draws) ** 2, axis=1)  # chi-square of each draw
    starts = draws[np.argsort(cost, kind="stable")[:MAP_STARTS]]

    fits = [least_squares_fit(res, x0, lo, hi, log_post.feasible) for x0 in starts]
    best_chi2, best = min(fits, key=lambda item: item[0])
    more = 0
    limit = far_above_noise(res.n_residuals, len(prior.names))
    for x0 in draws[np.argsort(cost, kind="stable")[MAP_STARTS:]] if best_chi2 > limit else ():
        fits.append(least_squares_fit(res, x0, lo, hi, log_post.feasible))
        more += 1
        if fits[-1][0] <= limit:
            break
    best_chi2, best = min(fits, key=lambda item: item[0])
    centre = best.x
    ball = np.clip(centre + width * laplace_draws(best.jac * width, rng, n_walkers), lo, hi)
    redrawn = 0
    for _ in range(100):
        outside = ~log_post.feasible(ball)
        if not outside.any():
            break
        redrawn += int(outside.sum())
        ball[outside] = np.clip(centre + width * laplace_draws(best.jac * width, rng, int(outside.sum())), lo, hi)
    record: dict[str, Any] = {
        "method": "map",
        "prior_draws": MAP_DRAWS,
        "least_squares_starts": MAP_STARTS,
        "optimum": {n: float(v) for n, v in zip(prior.names, prior.to_values(centre))},
        "chi_square": best_chi2,
        "chi_square_best_prior_draw": float(np.min(cost)),
        "residuals": int(best.fun.size),
        "more_fits": more,
        "fits": [{"chi_square": c, "status": int(f.status), "residual_evaluations": int(f.nfev),
                  "optimum": {n: float(v) for n, v in zip(prior.names, prior.to_values(f.x))}} for c, f in fits],
        "evaluations": res.evaluations,
        "forward_batches": res.batches,
        "failed_sets": res.failed,
        **({"infeasible_sets": res.infeasible, "walkers_redrawn_into_the_cut": redrawn} if log_post.spread_cut else {}),
        "ball_fraction_of_prior_width": MAP_BALL,
    }
    return ball, record


def refit_start(log_post: bayes.Posterior, x0: np.ndarray, n_walkers: int, rng: np.random.Generator
                ) -> tuple[np.ndarray, dict]:
    """The ``map`` start from least-squares fits that start at ``x0`` (sampled coordinates, (n_params,) or
    (k, n_params): one fit from each row, the lowest chi-square kept, the first of equals; e.g. the optimum before a
    change of the forward model): positions (n_walkers, n_params) and a record as ``map_start``'s (``refit_from``:
    the kept fit's x0 in CLI units; ``fits``: every fit, in the rows' order)."""
    prior = log_post.prior
    lo, hi = prior.lo_coord, prior.hi_coord
    width = hi - lo
    res = Residuals(log_post)
    starts = np.atleast_2d(x0)
    fits = [least_squares_fit(res, np.clip(x, lo, hi), lo, hi, log_post.feasible) for x in starts]
    kept = min(range(len(fits)), key=lambda k: fits[k][0])
    chi_square, fit = fits[kept]
    ball = np.clip(fit.x + width * laplace_draws(fit.jac * width, rng, n_walkers), lo, hi)
    for _ in range(100):
        outside = ~log_post.feasible(ball)
        if not outside.any():
            break
        ball[outside] = np.clip(fit.x + width * laplace_draws(fit.jac * width, rng, int(outside.sum())), lo, hi)
    names = prior.names

    def values(x: np.ndarray) -> dict[str, float]:
        return {n: float(v) for n, v in zip(names, prior.to_values(x))}

    return ball, {"method": "map", "prior_draws": 0, "least_squares_starts": len(fits), "more_fits": 0,
                  "refit_from": values(starts[kept]), "optimum": values(fit.x), "chi_square": chi_square,
                  "residuals": int(fit.fun.size),
                  "fits": [{"chi_square": c, "status": int(f.status), "residual_evaluations": int(f.nfev),
                            **({"refit_from": values(x)} if len(fits) > 1 else {}), "optimum": values(f.x)}
                           for x, (c, f) in zip(starts, fits)],
                  "evaluations": res.evaluations, "forward_batches": res.batches, "failed_sets": res.failed,
                  "ball_fraction_of_prior_width": MAP_BALL}


START_METHODS = {"map": map_start, "prior": prior_start}
"""``hmodel calibrate --start`` choices."""
