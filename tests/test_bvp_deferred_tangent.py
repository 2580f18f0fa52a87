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


def test_reused_tangent_converges_to_the_same_curve_with_fewer_tangents():
    steps = fe.isotropic_stage(P0, 4) + fe.shear_stage(P0, 8e-3, 8)
    runs = {}
    for reuse in (False, True):
        specimen = fe.BiaxialSpecimen(1, 2, newton_rtol=1e-5, reuse_tangent=reuse)
        material = HomogenisedMaterial(make_cell_model("dem"), orientation.orientations(12), h_cell(40.0),
                                       specimen.n_points)
        runs[reuse] = specimen.run(material, steps, scale=P0)
    fresh, reused = runs[False], runs[True]
    for r in reused:
        corrections = r.iterations - r.diagnostics["line_search_halvings"]
        assert r.diagnostics["tangents"] + r.diagnostics["tangents_reused"] == corrections
        assert r.residuals[-1] <= 1e-5 * P0
    assert all(r.diagnostics["tangents_reused"] == 0 for r in fresh)
    n_fresh = sum(r.diagnostics["tangents"] for r in fresh)
    n_reused = sum(r.diagnostics["tangents"] for r in reused)
    assert sum(r.diagnostics["tangents_reused"] for r in reused) > 0 and n_reused < n_fresh
    q = np.array([[r.sigma11 - r.sigma22 for r in run] for run in (fresh, reused)]) / P0
    assert q[0, -1] > 0.5  # sheared
    assert np.abs(q[0] - q[1]).max() <= 5e-5  # both within 5x the Newton tolerance (1e-5 of p0) of one curve


def test_cli_reuse_tangent_records_the_flag_and_the_counts(tmp_path, capsys):
    import json

    import h5py

    from homogenization.cli import bvp
    from warp_hcell.core.cli import run_main

    argv = ["--backend", "dem", "--alpha0", "40", "--p0", "2e5", "--eps-max", "0.004", "--increment", "1e-3",
            "--orientations", "12", "--elements", "1,2", "--iso-steps", "4", "--newton-rtol", "1e-5"]
    counts = {}
    for flag in ([], ["--reuse-tangent"]):
        out = tmp_path / ("reuse" if flag else "fresh")
        assert run_main(bvp.main, argv + flag + ["--out", str(out)]) == 0
        line = next(text for text in capsys.readouterr().out.splitlines() if "tangents computed" in text)
        computed, reused = (int(part.split()[-1]) for part in line.split("tangents computed ")[1].split(", reused"))
        counts[bool(flag)] = computed, reused
        with h5py.File(out / "run.h5") as f:
            assert json.loads(f.attrs["parameters"])["reuse_tangent"] is bool(flag)
    assert counts[False][1] == 0 and counts[True][1] > 0
    assert counts[True][0] < counts[False][0]
