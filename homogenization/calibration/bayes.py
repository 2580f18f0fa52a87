"""Prior, likelihood and posterior sampling of a calibration (emcee).

Sampled coordinates: each calibrated parameter in the units of the CLI flags (phi_g and
alpha0 [deg], kt_over_kn [-]) or, for a log-scaled prior (kn by default), its log10. The prior
is uniform in those coordinates between the bounds of ``Prior``.

Likelihood: independent Gaussian errors. A channel c (q, p or eps_v) of a test has the
standard deviation sigma_c = noise * max(abs(observed_c)), the same for all its points::

    log L = sum_tests sum_c sum_i [ -0.5 ((model_ci - observed_ci) / sigma_c)^2 - log(sigma_c) - 0.5 log(2 pi) ]

A parameter set whose forward model fails (NaN, e.g. p0 not reached) has log L = -inf.

Sampler: emcee's ensemble, its stretch move or differential evolution (``sampler_moves``; ``vectorize=True``:
the whole population of walkers is one call of the forward model, one batch of cells), its chain in emcee's HDF5
backend so that a run resumes where it stopped. With ``workers`` > 1 (analytical backend) a call's parameter
sets are shared among that many processes, in contiguous chunks (fewer sets than workers: its tests are): a set's
curves do not depend on the population it runs in (``forward``), so the curves are the same bits as in one
process (a least-squares start may still move in its last bits: scipy's arithmetic depends on where numpy placed
the residuals in memory).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np

from homogenization.calibration.data import CHANNELS, Measurement
from homogenization.calibration.forward import (DENSITY_PRIOR, INTERLOCKING_PRIOR, KN_EXPONENT, KN_EXPONENT_PRIOR,
                                                RULE_PRIOR, SPREAD, SPREAD_PRIOR, ForwardSettings, feasible, simulate)
from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import (
    PRIOR_BOUNDS_2D,
    PRIOR_BOUNDS_3D,
    PRIOR_BOUNDS_HERTZ_3D,
    ContactLaw,
    HertzMindlinLaw,
    check_alpha0_deg,
    check_positive,
)

DEFAULT_BOUNDS = {2: PRIOR_BOUNDS_2D, 3: PRIOR_BOUNDS_3D}
"""Default prior of each parameter by the dimension of the data (3 where any test is triaxial):
(low, high, log-uniform?) in CLI units (deg, N/m, -, deg); ``warp_hcell.core.parameters``."""
HERTZ_BOUNDS = {**PRIOR_BOUNDS_3D, **PRIOR_BOUNDS_HERTZ_3D}
"""Default prior of the Hertz-Mindlin law's calibration (triaxial data only): G [Pa], nu [-] from
``PRIOR_BOUNDS_HERTZ_3D``, phi_g and alpha0 as ``PRIOR_BOUNDS_3D``."""
DEFINED = {"phi_g": lambda v: ContactLaw(phi_g_deg=v), "kn": lambda v: check_positive("kn", v),
           "kt_over_kn": lambda v: check_positive("kt_over_kn", v), "alpha0": check_alpha0_deg,
           "shear_modulus": lambda v: check_positive("shear_modulus", v), "poisson": lambda v: HertzMindlinLaw(poisson=v)}
"""ValueError (one line) where a value of the parameter is outside the range where the cell and its contact law are
defined (``warp_hcell.core.parameters``): a prior file's bounds are checked with it."""
UNITS = {"phi_g": "deg", "kn": "N/m", "kt_over_kn": "-", "alpha0": "deg", "shear_modulus": "Pa", "poisson": "-",
         SPREAD: "deg", "e_min": "-", "e_max": "-", "alpha_c": "deg", "renewal_rate": "-",
         **{name: "-" for name in INTERLOCKING_PRIOR}, KN_EXPONENT: "-"}
"""Unit of each parameter in posterior.json and the figures."""
CONTRACTION_CONSTRAINED = 0.5
"""A parameter counts as constrained by the data where its posterior standard deviation is below
this fraction of its prior's (in the sampled coordinate) and the chain is not short (``summarise``) [-]."""


@dataclass(frozen=True)
class Prior:
    """Independent uniform priors of the calibrated parameters.

    Attributes:
        names: calibrated parameters, in sampling order.
        low, high: bounds in CLI units, shape (n_params,).
        log: whether the parameter is sampled as log10 (log-uniform prior), shape (n_params,).
    """

    names: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    log: np.ndarray

    @property
    def lo_coord(self) -> np.ndarray:
        """Lower bounds in sampled coordinates."""
        return np.where(self.log, np.log10(np.where(self.log, self.low, 1.0)), self.low)

    @property
    def hi_coord(self) -> np.ndarray:
        """Upper bounds in sampled coordinates."""
        return np.where(self.log, np.log10(np.where(self.log, self.high, 1.0)), self.high)

    def to_values(self, x: np.ndarray) -> np.ndarray:
        """Sampled coordinates (..., n_params) -> CLI units."""
        return np.where(self.log, 10.0 ** x, x)

    def to_coord(self, values: np.ndarray) -> np.ndarray:
        """CLI units (..., n_params) -> sampled coordinates."""
        return np.where(self.log, np.log10(np.where(self.log, values, 1.0)), values)

    def log_prob(self, x: np.ndarray) -> np.ndarray:
        """log prior density of sampled coordinates x, shape (n, n_params) -> (n,); -inf outside."""
        inside = np.all((x >= self.lo_coord) & (x <= self.hi_coord), axis=1)
        return np.where(inside, -float(np.sum(np.log(self.hi_coord - self.lo_coord))), -np.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n draws in sampled coordinates, shape (n, n_params)."""
        return rng.uniform(self.lo_coord, self.hi_coord, size=(n, len(self.names)))

    def to_dict(self) -> dict[str, dict[str, float | bool]]:
        """JSON form (the --prior FILE format)."""
        return {name: {"low": float(lo), "high": float(hi), "log": bool(lg)}
                for name, lo, hi, lg in zip(self.names, self.low, self.high, self.log)}


def make_prior(names: Sequence[str], path: Path | None = None, dim: int = 2, law: str = "linear") -> Prior:
    """The prior of ``names``: ``DEFAULT_BOUNDS[dim]`` (``HERTZ_BOUNDS`` for the Hertz-Mindlin
    ``law``), overridden by the JSON file ``path``.

    File: ``{"phi_g": [20, 40], "kn": {"low": 1e8, "high": 1e9, "log": true}}``; a list keeps the
    parameter's default scale. Parameters not calibrated may not appear.

    Args:
        dim: 3 where any test is triaxial (the ten-sphere cell: alpha0 >= ``Dimension.min_opening_deg``), else 2.

    Raises:
        ValueError: one line naming the file for a missing, malformed or inconsistent prior, bounds
            outside where the model is defined (``DEFINED``), or an alpha0 prior reaching below
            ``Dimension.min_opening_deg`` (dim 3).
    """
    if SPREAD in names and dim != 3:
        raise ValueError(f"{SPREAD}: a spread of opening angles is a parameter of the ten-sphere cell; calibrate it on "
                         f"triaxial data")
    defaults = {**(HERTZ_BOUNDS if law == HertzMindlinLaw.name else DEFAULT_BOUNDS[dim]), SPREAD: SPREAD_PRIOR,
                **DENSITY_PRIOR, **RULE_PRIOR, **INTERLOCKING_PRIOR, KN_EXPONENT: KN_EXPONENT_PRIOR}
    bounds = {name: defaults[name] for name in names}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"{path}: no such prior file")
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the prior: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError(f"{path}: the prior is a JSON object, parameter -> [low, high] or {{low, high, log}}")
        for name, spec in data.items():
            if name not in bounds:
                raise ValueError(f"{path}: {name!r} is not a calibrated parameter (--params {','.join(names)})")
            log = bounds[name][2]
            if isinstance(spec, dict):
                log = spec.get("log", log)
                spec = [spec.get("low"), spec.get("high")]
            if (not isinstance(spec, list) or len(spec) != 2 or not all(isinstance(v, (int, float)) for v in spec)
                    or not isinstance(log, bool)):
                raise ValueError(f"{path}: prior of {name!r} must be [low, high] or {{\"low\", \"high\", \"log\"}}")
            lo, hi = float(spec[0]), float(spec[1])
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi) or (log and lo <= 0.0):
                raise ValueError(f"{path}: prior of {name!r} needs finite low < high (and low > 0 if log)")
            for value in (lo, np.nextafter(hi, lo)) if name in DEFINED else ():
                try:
                    DEFINED[name](value)
                except ValueError as exc:
                    raise ValueError(f"{path}: the prior of {name!r}, [{lo:g}, {hi:g}], reaches where the model is "
                                     f"undefined: {exc}") from None
            bounds[name] = (lo, hi, log)
    if SPREAD in bounds and bounds[SPREAD][0] < 0.0:
        raise ValueError(f"{path}: the prior of {SPREAD} reaches below 0 deg (it is a half-width)")
    floor = dimension(dim).min_opening_deg
    if floor is not None and "alpha0" in bounds and bounds["alpha0"][0] < floor:
        raise ValueError(f"{path}: triaxial data: the ten-sphere cell needs alpha0 >= {floor:g} deg "
                         f"(below, its two planes overlap); give alpha0 a prior such as [{floor:g}, 85]")
    return Prior(tuple(names), np.array([bounds[n][0] for n in names]), np.array([bounds[n][1] for n in names]),
                 np.array([bounds[n][2] for n in names]))


def channel_sigma(test: Measurement, noise: float) -> dict[str, float]:
    """Standard deviation of each measured channel of ``test``: noise x its largest abs value."""
    return {c: noise * float(np.max(np.abs(v))) for c, v in test.observed.items()}


def channel_residuals(tests: Sequence[Measurement], curves: Sequence[Mapping[str, np.ndarray]],
                      noise: float) -> Iterator[tuple[float, np.ndarray]]:
    """(sigma_c, (model - observed) / sigma_c of shape (n, n_data)) of every test and channel, in order."""
    for test, model in zip(tests, curves):
        for c, sigma in channel_sigma(test, noise).items():
            yield sigma, (np.asarray(model[c]) - test.observed[c]) / sigma


def residuals(tests: Sequence[Measurement], curves: Sequence[Mapping[str, np.ndarray]], noise: float) -> np.ndarray:
    """Every residual of the likelihood, (model - observed) / sigma, of n model curves per test, shape
    (n, n_residuals): log L = -0.5 sum(residuals^2) + a constant, so least squares on them maximises L."""
    return np.concatenate([r for _, r in channel_residuals(tests, curves, noise)], axis=1)


def log_likelihood(tests: Sequence[Measurement], curves: Sequence[Mapping[str, np.ndarray]], noise: float) -> np.ndarray:
    """Gaussian log-likelihood (module docstring) of n model curves per test, shape (n,).

    Args:
        tests: the measurements.
        curves: per test, channel -> model values at the test's eps1, shape (n, n_data).
        noise: measurement error as a fraction of each channel's largest abs value [-].
    """
    total = None
    for sigma, r in channel_residuals(tests, curves, noise):
        term = -0.5 * np.sum(r * r, axis=1) - r.shape[1] * (math.log(sigma) + 0.5 * math.log(2.0 * math.pi))
        total = term if total is None else total + term
    return np.where(np.isfinite(total), total, -np.inf)


class Posterior:
    """log posterior of sampled coordinates, vectorised: the callable emcee samples.

    One call runs every test's forward model on the whole population, shared among ``workers`` processes on the
    analytical backend (module docstring; ``close`` stops them). Counted, not printed: ``n_sets`` parameter sets run
    by the forward model (start fits and checks included), ``n_fallback`` forward fallbacks
    (``forward.Curves.n_fallback``), ``n_jump`` drained increments solved at a jump, ``n_clip`` and
    ``n_renewal_clip`` the rules' clips (``forward.Curves``), ``n_failed`` sets
    whose forward model failed (log L = -inf), ``n_calls`` sets evaluated inside the prior, ``n_float_errors``
    numpy operations that overflowed, divided by zero or gave NaN (each worker's share counts its own). Where
    alpha0_spread is calibrated, sets with alpha0 - alpha0_spread < ALPHA_MIN_3D_DEG (``forward.feasible``) get
    -inf without a run (``n_infeasible``). ``correction`` (None, or per test channel -> (n_data,)) is added to
    every model curve (``resolution.correction``).
    """

    def __init__(self, tests: Sequence[Measurement], prior: Prior, settings: ForwardSettings, noise: float,
                 workers: int = 1) -> None:
        if workers < 1:
            raise ValueError(f"workers = {workers}: needs >= 1")
        self.tests = tuple(tests)
        self.prior = prior
        self.settings = settings
        self.noise = float(noise)
        self.workers = int(workers) if settings.backend == "analytical" else 1
        self._pool: ProcessPoolExecutor | None = None
        self.n_sets = 0
        self.n_fallback = 0
        self.n_jump = 0
        self.n_clip = 0
        self.n_renewal_clip = 0
        self.n_failed = 0
        self.n_calls = 0
        self.n_float_errors = 0
        self.n_infeasible = 0
        self.correction: list[dict[str, np.ndarray]] | None = None

    COUNTS = ("n_calls", "n_sets", "n_failed", "n_fallback", "n_jump", "n_clip", "n_renewal_clip", "n_float_errors",
              "n_infeasible")
    """The counters of the forward runs (``counts``): kept in the chain file, so that a resumed run adds to them."""

    def counts(self) -> dict[str, int]:
        """Every counter of ``COUNTS`` by name."""
        return {name: int(getattr(self, name)) for name in self.COUNTS}

    def take_counts(self) -> dict[str, int]:
        """``counts()``, the counters then set to 0 (the start's runs, kept apart from the sampler's)."""
        counts = self.counts()
        for name in self.COUNTS:
            setattr(self, name, 0)
        return counts

    def add_counts(self, counts: Mapping[str, int]) -> None:
        """Add ``counts`` (a ``counts()`` of an earlier process of the same chain; missing names: 0) to the counters."""
        for name in self.COUNTS:
            setattr(self, name, getattr(self, name) + int(counts.get(name, 0)))

    @property
    def spread_cut(self) -> bool:
        """Whether the prior is cut by alpha0 - alpha0_spread >= ALPHA_MIN_3D_DEG: alpha0_spread calibrated or fixed,
        and some test without its void ratio (a test that gives one runs at its map's alpha0, not the set's, and
        ``forward.simulate`` judges the spread there: NaN curves, a failed set)."""
        return ((SPREAD in self.prior.names or SPREAD in self.settings.fixed)
                and any(test.void_ratio is None for test in self.tests))

    def feasible(self, x: np.ndarray) -> np.ndarray:
        """Whether each set of sampled coordinates x (n, n_params) meets the prior's cut (class docstring), shape (n,);
        every set where there is none (``spread_cut``)."""
        values = self.prior.to_values(np.atleast_2d(x))
        if not self.spread_cut:
            return np.ones(values.shape[0], dtype=bool)
        ok = feasible({name: values[:, i] for i, name in enumerate(self.prior.names)}, self.settings)
        return np.ones(values.shape[0], dtype=bool) if ok is None else ok

    def curves(self, values: np.ndarray) -> list[dict[str, np.ndarray]]:
        """Model curves of parameter sets in CLI units, shape (n, n_params): per test, channel -> (n, n_data).

        With ``workers`` > 1 the sets go to the workers in contiguous chunks, or, with fewer sets than workers,
        the tests do (a least-squares fit's single sets)."""
        params = {name: values[:, i] for i, name in enumerate(self.prior.names)}
        n, every = values.shape[0], tuple(range(len(self.tests)))
        if self.workers > 1 and n >= self.workers:
            edges = np.linspace(0, n, self.workers + 1).round().astype(int)
            shares = [(every, a, b) for a, b in zip(edges[:-1], edges[1:])]
        elif self.workers > 1 and len(every) > 1:
            shares = [((k,), 0, n) for k in every]
        else:
            shares = [(every, 0, n)]
        jobs = [([self.tests[k] for k in tests], {name: v[a:b] for name, v in params.items()})
                for tests, a, b in shares]
        if len(shares) == 1:
            parts = [forward_share(*jobs[0], self.settings)]
        else:
            if self._pool is None:
                method = "fork" if sys.platform == "linux" else "spawn"
                self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context(method))
            futures = [self._pool.submit(forward_share, tests, chunk, self.settings) for tests, chunk in jobs]
            parts = [f.result() for f in futures]
        self.n_sets += n
        pieces: dict[int, list] = {k: [] for k in every}
        for (tests, _, _), (per_test, errors) in zip(shares, parts):
            self.n_float_errors += errors
            for k, piece in zip(tests, per_test):
                pieces[k].append(piece)
        out = []
        for k in every:
            self.n_fallback += sum(piece[1] for piece in pieces[k])
            self.n_jump += sum(piece[2] for piece in pieces[k])
            self.n_clip += sum(piece[3] for piece in pieces[k])
            self.n_renewal_clip += sum(piece[4] for piece in pieces[k])
            shift = self.correction[k] if self.correction is not None else {}
            channels = {name: np.concatenate([piece[0][name] for piece in pieces[k]]) for name in CHANNELS}
            out.append({name: c + shift[name] if name in shift else c for name, c in channels.items()})
        return out

    def close(self) -> None:
        """Stop the worker processes (if any were started); a later call starts them again."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        lp = self.prior.log_prob(x)
        inside = np.isfinite(lp)
        if self.spread_cut:
            cut = inside & ~self.feasible(x)
            self.n_infeasible += int(np.count_nonzero(cut))
            inside &= ~cut
        out = np.full(x.shape[0], -np.inf)
        if inside.any():
            values = self.prior.to_values(x[inside])
            ll = log_likelihood(self.tests, self.curves(values), self.noise)
            self.n_calls += int(inside.sum())
            self.n_failed += int(np.count_nonzero(~np.isfinite(ll)))
            out[inside] = lp[inside] + ll
        return out


def forward_share(tests: Sequence[Measurement], params: Mapping[str, np.ndarray], settings: ForwardSettings
                  ) -> tuple[list[tuple[dict[str, np.ndarray], int, int, int, int]], int]:
    """One worker's share of ``Posterior.curves``: per test (channel -> (n, n_data), fallbacks, jumps, interlocking
    and renewal clips: ``forward.Curves``' counts summed over the sets) of the sets
    ``params`` (name -> (n,)), and the numpy floating-point errors counted on the way (not printed)."""
    errors = [0]

    def count(kind: str, flag: int) -> None:
        errors[0] += 1

    out = []
    for test in tests:
        with np.errstate(all="call", call=count):
            c = simulate(test, params, settings)
        out.append(({name: c.channel(name) for name in CHANNELS}, int(c.n_fallback.sum()), int(c.n_jump.sum()),
                    int(c.n_clip.sum()), int(c.n_renewal_clip.sum())))
    return out, errors[0]


MOVES = {
    "stretch": "emcee's default stretch move (Goodman & Weare 2010): a walker moves along the line through another "
               "walker; the package's chains before this option",
    "de": "differential evolution: a walker moves along the difference of two others (0.8; DEMove, gamma "
          "2.38 / sqrt(2 n_params)) or by the snooker update (0.2; DESnookerMove), emcee's documented mix",
}
"""The ensemble moves of ``hmodel calibrate --moves`` (name -> what they do)."""


def sampler_moves(name: str) -> list | None:
    """emcee's ``moves`` argument of the named mix (``MOVES``): None for "stretch" (emcee's default
    ``StretchMove``, the same chain bit for bit), else (move, weight) pairs; every random draw of the moves
    comes from the sampler's ``random_state``, so a seeded chain is reproducible and resumes bit for bit.

    Raises:
        ValueError: ``name`` is not a key of ``MOVES``.
    """
    import emcee  # noqa: PLC0415 (only when a calibration runs)

    if name == "stretch":
        return None
    if name == "de":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    raise ValueError(f"moves {name!r}: one of {', '.join(MOVES)}")


def initial_walkers(log_post: Callable[[np.ndarray], np.ndarray], prior: Prior, n_walkers: int,
                    rng: np.random.Generator, oversample: int = 8) -> np.ndarray:
    """Starting ensemble: the ``n_walkers`` best of ``oversample`` x n_walkers prior draws (one batch)."""
    draws = prior.sample(rng, oversample * n_walkers)
    lp = log_post(draws)
    return draws[np.argsort(-lp, kind="stable")[:n_walkers]]


def summarise(samples: np.ndarray, prior: Prior, short: bool = False
              ) -> dict[str, dict[str, float | list[float] | str | bool | None]]:
    """posterior.json entries: mean, median, ci95 (2.5 and 97.5 % quantiles) in CLI units, and
    the contraction sd_post / sd_prior in the sampled coordinate (``constrained`` below
    ``CONTRACTION_CONSTRAINED``; ``verdict`` in words).

    Args:
        samples: posterior draws in sampled coordinates, shape (n_samples, n_params).
        short: the chain is short of its autocorrelation times (``diagnostics.chain_diagnostics``): its walkers may
            not have spread from their start yet, so a contraction below the threshold decides nothing
            (``constrained`` None, "undetermined: chain too short"); one above it stays "not constrained".
    """
    values = prior.to_values(samples)
    prior_sd = (prior.hi_coord - prior.lo_coord) / math.sqrt(12.0)
    out = {}
    for i, name in enumerate(prior.names):
        v = values[:, i]
        contraction = float(np.std(samples[:, i]) / prior_sd[i])
        constrained = None if short and contraction < CONTRACTION_CONSTRAINED else contraction < CONTRACTION_CONSTRAINED
        out[name] = {
            "mean": float(np.mean(v)),
            "median": float(np.median(v)),
            "ci95": [float(np.quantile(v, 0.025)), float(np.quantile(v, 0.975))],
            "unit": UNITS[name],
            "contraction": contraction,
            "constrained": constrained,
            "verdict": VERDICTS[constrained],
        }
    return out


VERDICTS = {True: "constrained", False: "not constrained", None: "undetermined: chain too short"}
"""``summarise``'s verdict of each ``constrained`` value."""


def correlations(samples: np.ndarray, prior: Prior) -> dict[str, float]:
    """Posterior correlation of every pair of parameters (sampled coordinates), "a:b" -> r."""
    r = np.corrcoef(samples, rowvar=False) if samples.shape[1] > 1 else np.ones((1, 1))
    names = prior.names
    return {f"{names[i]}:{names[j]}": float(r[i, j]) for i in range(len(names)) for j in range(i + 1, len(names))}


def identifiability_note(summary: Mapping[str, Mapping], corr: Mapping[str, float]) -> list[str]:
    """Plain sentences: which parameters the data constrain, which not, and strong trade-offs."""
    lines = []
    for name, s in summary.items():
        if s["constrained"] is None:
            lines.append(f"{name}: {VERDICTS[None]} (posterior sd = {s['contraction']:.2f} x prior sd so far; its "
                         f"walkers may still be spreading from their start: run more --steps)")
        elif s["constrained"]:
            lines.append(f"{name}: constrained (posterior sd = {s['contraction']:.2f} x prior sd)")
        else:
            lines.append(f"{name}: NOT constrained by these data (posterior sd = {s['contraction']:.2f} x prior sd); "
                         f"its interval mostly reflects the prior")
    for pair, r in corr.items():
        if abs(r) > 0.8:
            a, b = pair.split(":")
            lines.append(f"{a} and {b} trade off (correlation {r:+.2f}): the data fix a combination of them")
    return lines

