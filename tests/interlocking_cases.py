"""The small forward model and parameter sets shared by the interlocking mechanism tests (lag, softening, void-ratio
lag, mobilisation): two calibration sets of one 3D cell each, on a coarse rule that runs in seconds."""

from __future__ import annotations

import numpy as np

from homogenization.calibration import forward
from homogenization.calibration.interlocking import InterlockingFriction

SETTINGS = forward.ForwardSettings(increment=2e-3, iso_increment=1e-3, lebedev_order=5, n_spins=2, stress_rtol=1e-5)
"""The forward model's resolution: coarse, for speed (the mechanisms are compared on one model)."""
P_REF = 101325.0
"""The reference pressure of the mechanisms' pressure factors [Pa]."""
SETS = {"phi_g": np.array([30.0, 30.0]), "kn": np.array([5e7, 5e7]), "kt_over_kn": np.array([1.0, 1.0]),
        "e_min": np.array([0.45, 0.45]), "e_max": np.array([0.7, 0.7])}
"""Two parameter sets, alike (a test changes one mechanism's value in one of them)."""
FAST = ["--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none", "--resolution", "off", "-q"]
"""``hmodel calibrate`` flags for a run of seconds."""


class LagRecorder(InterlockingFriction):
    """The hook, recording each accepted increment's (lagged e before, strain before, J, strain and p after,
    lagged e after) in ``steps`` (a list the test sets)."""

    def advance(self, state):
        before = (self.e_lagged.copy(), self._strain.copy())
        state = super().advance(state)
        self.steps.append((*before, state.J.copy(), state.strain.copy(), self._mean(state.stress),
                           self.e_lagged.copy()))
        return state
