"""Stress control with several controlled components (a drained 3D step: sigma22 and sigma33) where the
response jumps across the target (``StressControl.solve``, ``_several_jump``): the recorded policy takes
the trial nearest the target and flags it; a smooth response converges unflagged; a target the material
cannot reach without a jump still raises ``ControlError``. The material is a linear one with a step in
sigma22 and sigma33 where the increment of eps22 passes a threshold, its tangent blind to the step (like a
meso-ANN cell whose equilibrium corrections land on another contact state)."""

from types import SimpleNamespace

import numpy as np
import pytest

from homogenization.element_test.plan import Plan
from homogenization.element_test.solver import STRICT, ControlError, StressControl
from warp_hcell.core.parameters import LoadingDefaults

STIFFNESS = np.array([[3e9, 1e9, 1e9], [1e9, 3e9, 1e9], [1e9, 1e9, 3e9]])
"""d sigma / d eps of the normal components [Pa] (the shear ones: 1e9 each)."""
P0 = 2e5


class SteppedPoints:
    """Material points (``MaterialPoints``' interface for ``StressControl``) of a linear material whose
    sigma22 and sigma33 rise by ``jump`` [Pa] where the increment's eps22 exceeds ``at``; ``saturate``
    caps the lateral stresses instead (a target out of reach)."""

    unit = "Pa"
    dim = 3

    def __init__(self, n: int, at: float, jump: np.ndarray, saturate: float | None = None) -> None:
        self.n, self.at, self.jump, self.saturate = n, at, np.asarray(jump, dtype=float), saturate
        self.stress = np.tile([P0, P0, P0, 0.0, 0.0, 0.0], (n, 1))
        self.peak = np.full(n, P0)
        self.trials = 0

    def trial(self, d: np.ndarray, *, with_tangent: bool = False):
        self.trials += 1
        tangent = np.zeros((self.n, 6, 6))
        tangent[:, :3, :3] = STIFFNESS
        tangent[:, 3:, 3:] = 1e9 * np.eye(3)
        stress = self.stress + np.einsum("pij,pj->pi", tangent, d)
        stress[:, 1:3] += self.jump * (d[:, 1:2] > self.at)
        if self.saturate is not None:
            stress[:, 1:3] = np.minimum(stress[:, 1:3], self.saturate)
        return SimpleNamespace(stress=stress, tangent=tangent if with_tangent else None, d=d.copy())

    def accept(self, update, mask=None) -> None:
        mask = np.ones(self.n, dtype=bool) if mask is None else mask
        self.stress = np.where(mask[:, None], update.stress, self.stress)


def _solve(points: SteppedPoints, axial: float = 1e-4):
    """One drained increment: eps11 += ``axial``, sigma22 = sigma33 = P0 held; (solved, the guess)."""
    d = np.zeros((points.n, 6))
    d[:, 0] = axial
    plan = Plan("shear", 1, d, np.array([1, 2]), np.full((points.n, 2), P0), np.full((points.n, 2), P0), held=True)
    return StressControl(points, STRICT).solve(d, plan, plan.target(0), None, "test"), d


def _threshold() -> float:
    """An eps22 increment where a step of 15 Pa in sigma22 and sigma33 leaves the target of a drained
    increment of 1e-4 along eps11 in the gap: 1.9e-9 below the jump-free solution's, about half the
    solution's shift by the step, so that no point on either side comes within 3 Pa of the target."""
    lateral = np.linalg.solve(STIFFNESS[1:, 1:], -STIFFNESS[1:, 0] * 1e-4)
    return float(lateral[0]) - 1.9e-9


def test_a_jump_across_the_target_takes_the_nearest_trial_and_is_flagged():
    tol = LoadingDefaults.stress_rtol * P0
    jump = np.array([15.0, 15.0])  # ~7 times the tolerance, like the hybrid's cells at a drained failure
    points = SteppedPoints(3, _threshold(), jump)
    solved, _ = _solve(points)
    residual = np.abs(points.stress[:, 1:3] - P0).max(axis=1)
    assert solved.jump.all()
    assert np.all(residual > tol)  # no trial met the tolerance: the response has no solution
    assert np.all(residual <= jump.max())  # the trial accepted lies next to the jump
    assert LoadingDefaults.max_newton_iterations < solved.calls <= LoadingDefaults.max_newton_iterations + 20  # the bisection


def test_a_smooth_response_converges_unflagged():
    points = SteppedPoints(2, 1.0, np.zeros(2))  # threshold never reached: linear
    solved, _ = _solve(points)
    assert not solved.jump.any()
    assert np.all(np.abs(points.stress[:, 1:3] - P0) <= LoadingDefaults.stress_rtol * P0)
    assert solved.calls < 5


def test_a_target_out_of_reach_without_a_jump_still_fails():
    points = SteppedPoints(2, 1.0, np.zeros(2), saturate=P0 - 100.0)  # the lateral stresses never reach p0
    with pytest.raises(ControlError, match="did not converge"):
        _solve(points, axial=-1e-4)
