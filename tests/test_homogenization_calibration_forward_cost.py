"""The batched forward model gives up on a point whose drained Newton iteration overflowed: the other
points' curves are unchanged and the batch no longer pays max_newton population updates per increment."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from homogenization.calibration import forward
from homogenization.element_test.points import MaterialPoints
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import ForwardSettings, simulate

NAMES = ("phi_g", "kn", "kt_over_kn", "alpha0")
DIVERGING = [38.464, 2.5929e9, 0.14, 72.422]
"""A set whose drained triaxial Newton iteration overflows (test_calibration_output_noise)."""
SANE = [19.443, 3.7078e8, 0.858, 60.347]


def run(monkeypatch, rows) -> tuple[forward.Curves, int]:
    calls = [0]
    trial = MaterialPoints.trial

    def counted(self, *args, **kwargs):
        calls[0] += 1
        return trial(self, *args, **kwargs)

    monkeypatch.setattr(MaterialPoints, "trial", counted)
    test = Measurement("x.csv", Path("x.csv"), True, 2e5, np.linspace(0.002, 0.01, 5), {}, dim=3)
    with np.errstate(all="ignore"):
        curves = simulate(test, dict(zip(NAMES, np.array(rows, dtype=float).T)),
                          ForwardSettings(lebedev_order=5, n_spins=2))
    return curves, calls[0]


def test_a_diverging_point_is_given_up_without_costing_the_batch(monkeypatch):
    alone, calls_alone = run(monkeypatch, [SANE])
    batch, calls_batch = run(monkeypatch, [SANE, DIVERGING])
    assert not np.isfinite(batch.q[1]).all() and batch.n_fallback[1] > 0
    np.testing.assert_allclose(batch.q[0], alone.q[0], rtol=1e-12)
    np.testing.assert_allclose(batch.eps_v[0], alone.eps_v[0], rtol=1e-12, atol=1e-15)
    assert batch.n_fallback[0] == alone.n_fallback[0] == 0
    n_shear = 10  # eps1 to 0.01 in increments of 1e-3
    # before: every increment after the overflow ran max_newton (30) population updates
    assert calls_batch <= calls_alone + ForwardSettings().max_newton + n_shear, (calls_alone, calls_batch)
