"""The small forward model and parameter sets shared by the interlocking mechanism tests (lag, softening, void-ratio
lag, mobilisation): two calibration sets of one 3D cell each, on a coarse rule that runs in seconds; and a calibration
of one mechanism's parameter replayed by hmodel triaxial (``calibrated_replay``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cli_checks import interlocking_data, replayed_shear

from homogenization.calibration import forward, posterior as post_mod
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import InterlockingFriction
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

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


def calibrated_replay(tmp_path: Path, name: str, values: str, start: float, prior: tuple[float, float] | None = None):
    """``hmodel calibrate --interlocking --params phi_g,NAME`` on ``cli_checks.interlocking_data`` (4 walkers, 2 steps,
    ``FAST``; ``--interlocking-values`` ``values``; started at phi_g = 30 and NAME = ``start``; NAME's prior
    (low, high) ``prior`` where given), then ``hmodel triaxial --posterior`` of it (``cli_checks.replayed_shear``).

    Returns:
        (the posterior (``calibration.posterior.read_posterior``), posterior.json as a dict, the replayed shear's
        q [Pa], the forward model's q at the posterior mean on the same strains, and the same with NAME = 0).
    """
    out = tmp_path / "cal"
    flags = []
    if prior is not None:
        (tmp_path / "prior.json").write_text(json.dumps({name: list(prior)}))
        flags = ["--prior", str(tmp_path / "prior.json")]
    assert run_main(calibrate.main, [
        "--data", str(interlocking_data(tmp_path / "t.csv")), "--params", f"phi_g,{name}", "--interlocking", *flags,
        "--interlocking-values", values, "--walkers", "4", "--steps", "2", "--start-point", f"phi_g=30,{name}={start}",
        *FAST, "--out", str(out)]) == 0
    post = post_mod.read_posterior(out)
    data = json.loads((out / "posterior.json").read_text())
    eps1, q = replayed_shear(out, tmp_path / "run")
    test = Measurement("t", Path("t.csv"), True, 2e5, eps1, {"q": q}, 3, 0.6)
    mean = {key: np.array([value]) for key, value in post.mean.items()}
    model = forward.simulate(test, mean, post.forward).q[0]
    without = forward.simulate(test, {**mean, name: np.zeros(1)}, post.forward).q[0]
    return post, data, q, model, without
