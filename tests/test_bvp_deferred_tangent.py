"""The DEM's tangent computed apart from its step: chunked, deferred by the material, skipped by the FE solver
where Newton needs none; every path gives the same numbers bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.fe import solver as fe
from homogenization.material import orientation
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.dem import cell as dem_cell
from warp_hcell.mesostructures.hcell import h_cell

P0 = 2e5


class EagerTangent:
    """The DEM backend without ``step_tangent``: the material asks every step for its tangent."""

    def __init__(self, model):
        self.model = model
        self.name = model.name

    def step(self, cells, d_eps, *, with_tangent=False):
        return self.model.step(cells, d_eps, with_tangent=with_tangent)

    def __getattr__(self, name):
        if name == "step_tangent":
            raise AttributeError(name)
        return getattr(self.model, name)


def sheared(n_points: int, model):
    """A material of ``n_points`` x 12 DEM cells compressed isotropically, and a shear increment of it."""
    material = HomogenisedMaterial(model, orientation.orientations(12), h_cell(40.0), n_points)
    state = material.update(material.init_state(), np.tile([2e-5, 2e-5, 0.0], (n_points, 1)),
                            with_tangent=False).state
    rng = np.random.default_rng(3)
    d_e = np.array([1e-3, -3e-4, 2e-4]) * (1.0 + 0.3 * rng.random((n_points, 3)))
    return material, state, d_e


def test_deferred_tangent_equals_the_steps_own():
    material, state, d_e = sheared(6, make_cell_model("dem"))
    assert material.defers_tangent
    eager = material.update(state, d_e, with_tangent=True)
    plain = material.update(state, d_e, with_tangent=False)
    assert plain.tangent is None
    deferred = material.tangent(state, d_e, plain)
    assert np.array_equal(deferred, eager.tangent)
    assert np.abs(eager.tangent).max() > 0.0
    # the tangent of another increment differs (the test can tell)
    other = material.update(state, 0.5 * d_e, with_tangent=False)
    assert not np.allclose(material.tangent(state, 0.5 * d_e, other), eager.tangent, rtol=1e-6, atol=0.0)


def test_chunked_tangent_equals_one_chunk(monkeypatch):
    model = make_cell_model("dem", threads=2)
    material, state, d_e = sheared(10, model)  # 120 cells
    update = material.update(state, d_e, with_tangent=False)
    whole = model.step_tangent(state.cells, update.state.cells)
    monkeypatch.setattr(dem_cell, "TANGENT_CHUNK", 7)  # 18 chunks, the last of 1 cell, on two threads
    chunked = model.step_tangent(state.cells, update.state.cells)
    assert chunked.shape == (120, 2, 2)
    assert np.array_equal(chunked, whole)


def test_solver_skips_the_tangents_newton_does_not_use():
    steps = fe.isotropic_stage(P0, 4) + fe.shear_stage(P0, 3e-3, 3)
    runs = {}
    for name, model in (("deferred", make_cell_model("dem")), ("eager", EagerTangent(make_cell_model("dem")))):
        specimen = fe.BiaxialSpecimen(1, 2, newton_rtol=1e-5)
        material = HomogenisedMaterial(model, orientation.orientations(12), h_cell(40.0), specimen.n_points)
        assert material.defers_tangent == (name == "deferred")
        runs[name] = specimen.run(material, steps, scale=P0)
    deferred, eager = runs["deferred"], runs["eager"]
    for a, b in zip(deferred, eager):
        assert np.array_equal(a.stress, b.stress) and np.array_equal(a.displacement, b.displacement)
        assert a.iterations == b.iterations
        # one tangent per correction, none for the converged iterate; the eager run pays one per update
        assert a.diagnostics["tangents"] == a.iterations - a.diagnostics["line_search_halvings"]
        assert b.diagnostics["tangents"] == b.iterations + 1
    assert sum(r.iterations for r in deferred) >= 3  # the programme needed corrections
    assert (deferred[-1].sigma11 - deferred[-1].sigma22) > 0.1 * P0  # and was sheared


if __name__ == "__main__":
    pytest.main([__file__])
