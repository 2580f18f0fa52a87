"""Calibration output: floating-point errors of diverging forward runs are counted, not printed;
stuck walkers come with advice."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from homogenization.calibration import bayes, report
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import ForwardSettings, simulate


def test_forward_float_errors_are_counted_not_warned():
    """A drained triaxial test of an extreme parameter set (alpha0 = 72 deg, kt/kn = 0.14): its 2 x 2
    Newton iteration diverges and numpy overflows; the posterior counts those operations and no
    RuntimeWarning escapes (the forward model alone does warn)."""
    names = ("phi_g", "kn", "kt_over_kn", "alpha0")
    prior = bayes.make_prior(names)
    eps1 = np.linspace(0.002, 0.01, 5)
    test = Measurement("x.csv", Path("x.csv"), True, 2e5, eps1, {"q": 1e5 * eps1}, dim=3)
    posterior = bayes.Posterior([test], prior, ForwardSettings(lebedev_order=5, n_spins=2), noise=0.02)
    values = np.array([[38.464, 2.5929e9, 0.14, 72.422], [19.443, 3.7078e9, 0.858, 60.347]])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        simulate(test, dict(zip(names, values.T)), posterior.settings)  # the forward model alone warns
    assert [w for w in caught if issubclass(w.category, RuntimeWarning)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        posterior(prior.to_coord(values))
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert posterior.n_float_errors > 0


def _result(stuck: int, float_errors: int) -> dict:
    return {
        "posterior": {"phi_g": {"mean": 25.0, "median": 25.0, "ci95": [24.0, 26.0], "unit": "deg"}},
        "identifiability": [],
        "misfit_rms_over_sigma": {},
        "sampler": {"steps": 500, "walkers": 32, "acceptance_fraction": 0.39, "stuck_walkers_left_out": stuck},
        "forward_model": {"evaluations": 16032, "fallbacks": 28, "interlocking_clips": 3, "renewal_clips": 5,
                          "failed": 2, "floating_point_errors": float_errors},
    }


def test_summary_reports_float_errors_and_advises_on_stuck_walkers():
    lines = report.summary_lines(_result(6, 41))
    assert ("forward fallbacks 28 in 16032 evaluations, jumps 0, clips: interlocking 3, renewal 5, failed sets 2, "
            "floating-point errors 41") in lines[-2]
    assert lines[-1].startswith("6 of 32 walkers stayed where the posterior is below exp(-20)")
    assert "--prior" in lines[-1] and "--walkers" in lines[-1]
    quiet = report.summary_lines(_result(0, 0))
    assert quiet[-1].startswith("sampler: ") and "floating-point errors 0" in quiet[-1]


def test_corner_panels_without_contours_are_counted_not_logged(capsys, caplog):
    """Three parameters whose 60 samples take two distinct values each (a stalled chain): ``corner`` finds
    too few points for the contours of each of the 3 panels; they are counted, none is logged or printed,
    and the summary says so. 4000 samples of a Gaussian: no such panel."""
    prior = bayes.make_prior(("phi_g", "kt_over_kn", "alpha0"))
    stalled = np.repeat(np.array([[25.0, 0.5, 55.0], [25.0001, 0.5001, 55.0001]]), 30, axis=0)
    with caplog.at_level("WARNING"):
        _, bare = report.corner_figure(stalled, prior)
        _, none = report.corner_figure(np.random.default_rng(0).normal([25.0, 0.5, 55.0], 0.1, (4000, 3)), prior)
    assert (bare, none) == (3, 0)
    assert not [r for r in caplog.records if "contours" in r.getMessage()]
    assert "contours" not in capsys.readouterr().err
    result = _result(0, 0)
    result["posterior"] = {n: result["posterior"]["phi_g"] for n in ("phi_g", "kt_over_kn", "alpha0")}
    result["sampler"]["corner_panels_without_contours"] = bare
    assert "corner.png: 3 of 3 panels without contours (too few distinct samples: a short chain)" in report.summary_lines(result)
