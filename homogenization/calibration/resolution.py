"""Whether a calibration's forward model resolves its data, and the misfit measured against the noise.

``check(log_post, x, where)`` compares, at the parameter set x (sampled coordinates), the forward
model of ``log_post`` with two refined ones (``refined``): the strain increments halved (shear and
isotropic) and the orientations doubled (2D: ``n_orientations`` x 2; 3D: the Lebedev order raised
two steps of ``LEBEDEV_ORDERS``). For each knob and each test:channel it reports the rms of (model -
refined) over the likelihood's sigma, and the linearised shift of every parameter that this error
causes, in posterior standard deviations: delta = (J^T J)^-1 J^T e / sd, J the Jacobian of the
residuals at x (forward differences of ``start.MAP_STEP`` x the prior's width, one batch), sd =
sqrt(diag (J^T J)^-1). One refinement's difference is not the model's error: for a knob converging
at order p (``ORDER``) the error is about 2^p / (2^p - 1) times it (Richardson), and the knobs'
errors add. The check's error estimate of each test:channel (rms) and parameter (shift) is the sum
over the knobs of that factor times the abs difference; it passes where every rms estimate is below
``RMS_TOLERANCE`` and every shift estimate below ``SHIFT_TOLERANCE``: with more data points the
second is the stricter one.

``reference(log_post, x)`` refines every knob whose own error estimate reaches half a tolerance (the
one with the larger estimate where none does), one step at a time (each step a ``Check``, at most
``MAX_REFINEMENTS``), until the check passes: that model is the reference.
``correction(log_post, reference, x)``: the reference's curves minus the model's at x, which
``bayes.Posterior.correction`` adds to every curve, so that a chain runs at the model's cost with
the reference's accuracy near x; ``against_reference(log_post, reference, x, where)`` checks it
(the comparison "reference": (corrected model - reference) at x, rms and shift as above).

``misfit(log_post, x)``: chi-square of the residuals at x, its reduced value chi^2 / (n - k), and
whether it is far above the noise (above the 0.999 quantile of chi-square with n - k degrees of
freedom), with the model error (fraction of each channel's scale, added in quadrature to the
noise) that would bring the reduced chi-square to 1.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from homogenization.calibration import bayes
from homogenization.calibration.forward import ForwardSettings
from homogenization.material.orientation import LEBEDEV_ORDERS

RMS_TOLERANCE = 0.3
"""Largest estimated rms error / sigma of any test and channel that passes the check [-]."""
SHIFT_TOLERANCE = 0.2
"""Largest estimated shift of any parameter by that error, in posterior standard deviations, that passes [-]:
a bias of b sd lowers a 95 % interval's coverage to Phi(1.96 - b) - Phi(-1.96 - b)."""
MAX_REFINEMENTS = 8
"""Refinements ``reference`` makes at most before it gives up (``ResolutionError``) [-]."""
KNOBS = ("increment", "orientations")
"""The forward model's discretisation knobs that ``refined`` refines."""
MISFIT_QUANTILE = 0.999
"""Chi-square quantile above which a misfit counts as far above the noise [-]."""
ORDER = {"increment": 1, "orientations": 2}
"""Order of convergence of each knob [-]: the strain increments' explicit integration is first order, the
orientations' quadrature second; ``richardson`` turns one refinement's difference into an error estimate."""


def richardson(knob: str) -> float:
    """Factor from one refinement's difference to the error estimate of ``knob``: 2^p / (2^p - 1), p its
    ``ORDER``; 1 for a comparison with a reference ("reference") [-]."""
    p = ORDER.get(knob)
    return 1.0 if p is None else 2.0 ** p / (2.0 ** p - 1.0)


def refined(settings: ForwardSettings, knob: str) -> ForwardSettings:
    """``settings`` with ``knob`` refined: "increment" halves increment and iso_increment; "orientations"
    doubles n_orientations (2D), and raises lebedev_order two steps of ``LEBEDEV_ORDERS`` and doubles n_spins
    (3D: both factors of the product rule)."""
    if knob == "increment":
        return replace(settings, increment=settings.increment / 2.0, iso_increment=settings.iso_increment / 2.0)
    higher = [o for o in LEBEDEV_ORDERS if o > settings.lebedev_order]
    return replace(settings, n_orientations=2 * settings.n_orientations, n_spins=2 * settings.n_spins,
                   lebedev_order=higher[1] if len(higher) > 1 else (higher[0] if higher else settings.lebedev_order))


def knob_settings(settings: ForwardSettings) -> dict[str, float]:
    """The discretisation settings of ``settings`` that ``refined`` changes, for run.json."""
    return {"increment": settings.increment, "iso_increment": settings.iso_increment,
            "n_orientations": settings.n_orientations, "lebedev_order": settings.lebedev_order,
            "n_spins": settings.n_spins}


@dataclass
class Check:
    """One resolution check (module docstring).

    Attributes:
        where: "start" or "optimum".
        at: the parameter set checked, CLI units.
        settings: ``knob_settings`` of the model checked.
        rms_over_sigma: knob -> "test:channel" -> rms((model - refined) / sigma) [-].
        rms_fraction_of_scale: the same as a fraction of the channel's largest abs value [-].
        shift_over_sd: knob -> parameter -> linearised shift [posterior sd].
        seconds: wall time of the check [s].
    """

    where: str
    at: dict[str, float]
    settings: dict[str, float]
    rms_over_sigma: dict[str, dict[str, float]]
    rms_fraction_of_scale: dict[str, dict[str, float]]
    shift_over_sd: dict[str, dict[str, float]]
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def worst_rms(self, knob: str | None = None) -> float:
        """Largest rms / sigma over tests and channels (of ``knob``, or of any) [-]."""
        knobs = [knob] if knob else list(self.rms_over_sigma)
        return max((v for k in knobs for v in self.rms_over_sigma[k].values()), default=0.0)

    def worst_shift(self, knob: str | None = None) -> float:
        """Largest abs shift over parameters (of ``knob``, or of any) [posterior sd]."""
        knobs = [knob] if knob else list(self.shift_over_sd)
        return max((abs(v) for k in knobs for v in self.shift_over_sd[k].values()), default=0.0)

    def error_rms(self) -> dict[str, float]:
        """Error estimate of each test:channel: sum over knobs of ``richardson`` x rms / sigma [-]."""
        keys = next(iter(self.rms_over_sigma.values()), {})
        return {key: sum(richardson(k) * v[key] for k, v in self.rms_over_sigma.items()) for key in keys}

    def error_shift(self) -> dict[str, float]:
        """Error estimate of each parameter's shift: sum over knobs of ``richardson`` x abs shift [posterior sd]."""
        names = next(iter(self.shift_over_sd.values()), {})
        return {n: sum(richardson(k) * abs(v[n]) for k, v in self.shift_over_sd.items()) for n in names}

    @property
    def passed(self) -> bool:
        """Whether every error estimate (rms and shift) is below its tolerance."""
        return (max(self.error_rms().values(), default=0.0) < RMS_TOLERANCE
                and max(self.error_shift().values(), default=0.0) < SHIFT_TOLERANCE)

    def _share(self, knob: str) -> float:
        """``knob``'s error estimate against half of each tolerance (its share) [-]."""
        f = richardson(knob)
        return max(f * self.worst_rms(knob) / RMS_TOLERANCE, f * self.worst_shift(knob) / SHIFT_TOLERANCE) * 2.0

    @property
    def knobs_to_refine(self) -> list[str]:
        """The knobs whose own error estimate reaches half a tolerance, or else the ``worst_knob``."""
        failing = [k for k in KNOBS if k in self.rms_over_sigma and self._share(k) >= 1.0]
        return failing or [self.worst_knob]

    @property
    def worst_knob(self) -> str:
        """The knob whose error estimate is the larger (measured against the tolerances)."""
        return max([k for k in KNOBS if k in self.rms_over_sigma], key=self._share)

    def to_dict(self) -> dict[str, Any]:
        """run.json's form, with ``passed``, the worst values and the tolerances."""
        return {"where": self.where, "at": self.at, "settings": self.settings, "rms_over_sigma": self.rms_over_sigma,
                "rms_fraction_of_scale": self.rms_fraction_of_scale, "shift_over_sd": self.shift_over_sd,
                "worst_rms_over_sigma": self.worst_rms(), "worst_shift_over_sd": self.worst_shift(),
                "error_rms_over_sigma": self.error_rms(), "error_shift_over_sd": self.error_shift(),
                "richardson": {k: richardson(k) for k in self.rms_over_sigma}, "passed": self.passed,
                "rms_tolerance": RMS_TOLERANCE, "shift_tolerance": SHIFT_TOLERANCE,
                "seconds": self.seconds, **self.extra}

    def line(self) -> str:
        """One status line: the error of each knob at its worst test:channel and parameter."""
        parts = []
        for knob in self.rms_over_sigma:
            key = max(self.rms_over_sigma[knob], key=self.rms_over_sigma[knob].get)
            parts.append(f"{knob} {self.rms_over_sigma[knob][key]:.2f} sigma rms ({key}, "
                         f"{100 * self.rms_fraction_of_scale[knob][key]:.2f} % of its scale), parameter shift "
                         f"{self.worst_shift(knob):.2f} sd")
        s = self.settings
        rms, shift = self.error_rms(), self.error_shift()
        return (f"forward-model resolution at the {self.where} (increment {s['increment']:g}, {s['n_orientations']} "
                f"orientations (2D) / Lebedev {s['lebedev_order']} x {s['n_spins']} spins (3D)), its difference to "
                + ("a refined one: " if "reference" not in self.rms_over_sigma else "the reference: ") + "; ".join(parts)
                + f"; estimated error {max(rms.values(), default=0.0):.2f} sigma rms, parameter shift "
                f"{max(shift.values(), default=0.0):.2f} sd -> {'resolved' if self.passed else 'NOT resolved'} "
                f"(tolerances {RMS_TOLERANCE:g} sigma, {SHIFT_TOLERANCE:g} sd)")


def _channel_rms(log_post: bayes.Posterior, a: list, b: list) -> dict[str, float]:
    out = {}
    tests = log_post.tests
    sigma_a = bayes.channel_residuals(tests, a, log_post.noise)
    sigma_b = bayes.channel_residuals(tests, b, log_post.noise)
    keys = [f"{t.name}:{c}" for t in tests for c in t.observed]
    for key, (_, ra), (_, rb) in zip(keys, sigma_a, sigma_b):
        d = ra[0] - rb[0]
        out[key] = float(np.sqrt(np.mean(d * d)))
    return out


def jacobian(log_post: bayes.Posterior, x: np.ndarray) -> np.ndarray:
    """Residuals' Jacobian at x (sampled coordinates), forward differences of ``start.MAP_STEP`` x the
    prior's width (inwards at the upper bound), one batch; shape (n_residuals, n_params)."""
    from homogenization.calibration.start import MAP_STEP  # noqa: PLC0415

    prior = log_post.prior
    step = MAP_STEP * (prior.hi_coord - prior.lo_coord)
    step = np.where(x + step > prior.hi_coord, -step, step)
    sets = np.vstack([x, x + np.diag(step)])
    r = bayes.residuals(log_post.tests, log_post.curves(prior.to_values(sets)), log_post.noise)
    return ((r[1:] - r[0]) / step[:, None]).T


def check(log_post: bayes.Posterior, x: np.ndarray, where: str,
          against: ForwardSettings | None = None) -> Check:
    """The resolution check of ``log_post``'s forward model (with its correction, if any) at ``x``
    (sampled coordinates, shape (n_params,)): against its two refined models, or against the model
    ``against`` (comparison "reference")."""
    started = time.perf_counter()
    prior, settings = log_post.prior, log_post.settings
    values = prior.to_values(np.atleast_2d(x))
    with np.errstate(all="ignore"):
        base = log_post.curves(values)
        jac = jacobian(log_post, np.asarray(x, dtype=np.float64))
    jtj_inv = np.linalg.pinv(jac.T @ jac)
    sd = np.sqrt(np.maximum(np.diag(jtj_inv), 0.0))
    rms, fraction, shift = {}, {}, {}
    comparisons = {"reference": against} if against is not None else {k: refined(settings, k) for k in KNOBS}
    for knob, other in comparisons.items():
        fine = bayes.Posterior(log_post.tests, prior, other, log_post.noise)
        with np.errstate(all="ignore"):
            curves = fine.curves(values)
        rms[knob] = _channel_rms(log_post, base, curves)
        fraction[knob] = {k: v * log_post.noise for k, v in rms[knob].items()}
        e = bayes.residuals(log_post.tests, base, log_post.noise)[0] - \
            bayes.residuals(log_post.tests, curves, log_post.noise)[0]
        delta = jtj_inv @ (jac.T @ np.nan_to_num(e))
        shift[knob] = {name: float(d / s) if s > 0 else 0.0 for name, d, s in zip(prior.names, delta, sd)}
    return Check(where, {n: float(v) for n, v in zip(prior.names, values[0])}, knob_settings(settings), rms, fraction,
                 shift, time.perf_counter() - started)


class ResolutionError(RuntimeError):
    """``reference`` found no model that passes within ``MAX_REFINEMENTS`` refinements."""


def reference(log_post: bayes.Posterior, x: np.ndarray, where: str = "start",
              max_refinements: int = MAX_REFINEMENTS) -> tuple[ForwardSettings, list[Check]]:
    """The reference model at ``x`` (module docstring) and the checks made on the way (the first: of
    ``log_post``'s own model, without its correction).

    Raises:
        ResolutionError: no model passed within ``max_refinements`` refinements (its message names the last).
    """
    probe = bayes.Posterior(log_post.tests, log_post.prior, log_post.settings, log_post.noise)
    checks = [check(probe, x, where)]
    while not checks[-1].passed:
        if len(checks) > max_refinements:
            raise ResolutionError(checks[-1].line())
        settings = probe.settings
        for knob in checks[-1].knobs_to_refine:
            settings = refined(settings, knob)
        probe = bayes.Posterior(probe.tests, probe.prior, settings, probe.noise)
        checks.append(check(probe, x, where))
    return probe.settings, checks


def correction(log_post: bayes.Posterior, settings: ForwardSettings, x: np.ndarray) -> list[dict[str, np.ndarray]]:
    """Per test, channel -> the curve of ``settings`` minus that of ``log_post``'s model (without its
    correction) at ``x`` (sampled coordinates), shape (n_data,): ``bayes.Posterior.correction``."""
    values = log_post.prior.to_values(np.atleast_2d(x))
    plain = bayes.Posterior(log_post.tests, log_post.prior, log_post.settings, log_post.noise)
    fine = bayes.Posterior(log_post.tests, log_post.prior, settings, log_post.noise)
    with np.errstate(all="ignore"):
        a, b = plain.curves(values), fine.curves(values)
    return [{c: np.nan_to_num(b_t[c][0] - a_t[c][0]) for c in a_t} for a_t, b_t in zip(a, b)]


@dataclass(frozen=True)
class Misfit:
    """The misfit at a parameter set against the noise (module docstring).

    Attributes:
        chi_square: sum of squared residuals [-]; residuals: their number; parameters: calibrated ones.
        reduced: chi_square / (residuals - parameters) [-].
        limit: the ``MISFIT_QUANTILE`` quantile of chi-square / (residuals - parameters) [-].
        noise: the likelihood's sigma as a fraction of each channel's scale (noise and model error) [-].
        suggested_model_error: the model error (fraction) that brings ``reduced`` to 1, 0 if it is below [-].
    """

    chi_square: float
    residuals: int
    parameters: int
    reduced: float
    limit: float
    noise: float
    suggested_model_error: float

    @property
    def far_above_noise(self) -> bool:
        """Whether the reduced chi-square is above ``limit``."""
        return self.reduced > self.limit

    def to_dict(self) -> dict[str, Any]:
        return {"chi_square": self.chi_square, "residuals": self.residuals, "parameters": self.parameters,
                "reduced_chi_square": self.reduced, "limit": self.limit, "quantile": MISFIT_QUANTILE,
                "far_above_noise": self.far_above_noise, "suggested_model_error": self.suggested_model_error}

    def warning(self, measurement_noise: float) -> str | None:
        """One warning line where the misfit is far above the noise; None otherwise."""
        if not self.far_above_noise:
            return None
        return (f"warning: the fit misses the data by far more than their noise: reduced chi-square "
                f"{self.reduced:.2f} at the optimum (rms misfit {math.sqrt(self.reduced):.2f} sigma; above "
                f"{self.limit:.2f}, the {100 * MISFIT_QUANTILE:g} % quantile for {self.residuals} residuals): the model "
                f"cannot describe these data within a noise of {self.noise:g}, so the 95 % intervals, which assume "
                f"it can, are too narrow (by about {math.sqrt(self.reduced):.1f} x) and may miss the truth; add "
                f"--model-error {self.suggested_model_error:.3g} (in quadrature with --noise {measurement_noise:g}) "
                f"to widen them, or check the forward model and the data")


def misfit(log_post: bayes.Posterior, x: np.ndarray, measurement_noise: float) -> Misfit:
    """The ``Misfit`` of ``log_post`` at ``x`` (sampled coordinates); ``measurement_noise``: --noise [-]."""
    from scipy.stats import chi2  # noqa: PLC0415

    with np.errstate(all="ignore"):
        r = bayes.residuals(log_post.tests, log_post.curves(log_post.prior.to_values(np.atleast_2d(x))),
                            log_post.noise)[0]
    n, k = r.size, len(log_post.prior.names)
    dof = max(n - k, 1)
    chi_square = float(np.sum(r * r))
    reduced = chi_square / dof
    sigma = log_post.noise
    suggested = math.sqrt(max(sigma * sigma * reduced - measurement_noise ** 2, 0.0)) if reduced > 1.0 else 0.0
    return Misfit(chi_square, n, k, reduced, float(chi2.ppf(MISFIT_QUANTILE, dof)) / dof, sigma, suggested)
