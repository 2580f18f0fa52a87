"""3D DEM backend: the Warp kernel against the numpy oracle bit for bit, and the cell contract.

The oracle test uses a small five-sphere cell (four driven spheres at the corners of a
tetrahedron, one free sphere between them, touching all four) whose free sphere moves in every
direction: the vector tangential springs turn in their planes, stick and slide.
"""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np
import pytest

import dem_oracle3d
from tangent_fd import fd_tangent_fixed_schedule, relative_error
from homogenization.backends import make_cell_model
from warp_hcell.core.parameters import HERTZ_DT_OVERLAP, ContactLaw, DemSettings, HertzMindlinLaw
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.mesostructure import Mesostructure


def tetrahedral_cell() -> Mesostructure:
    """Four driven spheres (r = 0.5) at the corners of an irregular tetrahedron inscribed in the unit sphere,
    a free sphere (r = 0.5) at its centre touching all four: its contacts carry unequal forces."""
    corners = np.array([[1.0, 0.9, 1.1], [1.2, -1.0, -0.8], [-0.9, 1.0, -1.0], [-1.0, -1.1, 0.9]])
    corners /= np.linalg.norm(corners, axis=1, keepdims=True)
    radius = np.full(4, 0.5)
    centre_radius = 0.5
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    faces = np.array([f if np.dot(np.cross(corners[f[1]] - corners[f[0]], corners[f[2]] - corners[f[0]]),
                                  corners[f].mean(axis=0)) > 0 else f[::-1] for f in faces])
    return Mesostructure(name="tetrahedron", radius=np.append(radius, centre_radius),
                         position=np.vstack([corners, [0.0, 0.0, 0.0]]),
                         driven=np.array([[True] * 3] * 4 + [[False] * 3]),
                         pairs=np.array(list(combinations(range(5), 2))), outer=faces,
                         cell_size=np.ptp(corners, axis=0))


def test_the_warp_kernel_equals_the_numpy_oracle_bit_for_bit():
    meso = tetrahedral_cell()
    dem = make_cell_model("dem", dim=3, threads=1)
    n = 6
    state = dem.init_state(meso, n)
    model = state.model
    constants = {name: getattr(model, name).numpy() for name in
                 ("radius", "inv_mass", "reference_position", "reference_cell_size", "dt", "force_floor")}
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(n, 3))
    branches = set()
    for k in range(50):
        d = (3e-4 if k < 30 else -3e-4) * direction + (2e-4 if k < 8 else 0.0)
        arrays = {**constants, **{name: value for name, value in state.dem.to_numpy().items()
                                  if name in ("position", "velocity", "shear_force", "cell_size")}}
        expected = dem_oracle3d.step(arrays, d, pairs=meso.pairs, driven=meso.driven, faces=meso.outer,
                                     law=dem.contact_law, settings=dem.settings)
        state, _ = dem.step(state, d)
        got = state.dem.to_numpy()
        for name, value in expected.items():
            np.testing.assert_array_equal(got["area" if name == "volume" else name], value, err_msg=f"{name}, step {k}")
        shear = np.linalg.norm(got["shear_force"], axis=-1)
        normal = np.maximum(-np.einsum("cpa,cpa->cp", got["contact_force"], _units(got["position"], meso.pairs)), 0.0)
        branches |= {"stick" if s < 0.99 * dem.contact_law.mu * f else "slide"
                     for s, f in zip(shear.ravel(), normal.ravel()) if f > 0.0}
    assert branches == {"stick", "slide"}
    assert (got["converged"] == 1).all()


def _units(position: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    branch = position[:, pairs[:, 1]] - position[:, pairs[:, 0]]
    return branch / np.linalg.norm(branch, axis=-1, keepdims=True)


def test_a_cells_step_does_not_depend_on_its_batch_and_states_round_trip():
    dem = make_cell_model("dem", dim=3, threads=2)
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    n = 5
    state = dem.init_state(meso, n)
    rng = np.random.default_rng(1)
    for _ in range(12):
        state, _ = dem.step(state, 2e-4 * rng.normal(size=(n, 3)) + 1e-4)
    d = 1e-4 * rng.normal(size=(n, 3))
    whole = dem.step(state, d)[1].moment
    index = np.array([3, 0, 3])
    part = dem.step(dem.take(state, index), d[index])[1].moment
    np.testing.assert_array_equal(part, whole[index])
    again = dem.state_from_arrays(dem.state_to_arrays(state))
    np.testing.assert_array_equal(dem.step(again, d)[1].moment, whole)


def test_3d_increments_are_checked():
    dem = make_cell_model("dem", dim=3)
    state = dem.init_state(resolve_mesostructure("hcell3d:alpha0=55"), 2)
    with pytest.raises(ValueError, match=r"expected \(2, 3\)"):
        dem.step(state, np.zeros((2, 2)))
    assert DemSettings().force_tolerance > 0 and math.isfinite(ContactLaw().mu)


def test_the_condensed_tangent_equals_central_differences_with_sticking_and_sliding_contacts():
    """Driven slowly (1e-8 per substep), relaxed tightly and with the driving schedule held over the
    stencil (``tangent_fd.fd_tangent_fixed_schedule``: the last, shorter substep otherwise changes the
    sliding state), the condensed tangent matches central differences: to 1e-5 where every contact
    sticks, to 1e-3 in slide (where the relaxation swings contacts about the cap)."""
    from warp_hcell.dem.tangent import sliding_contacts_3d

    fine = DemSettings(strain_per_substep=1e-8, refined_strain_per_substep=1e-8, force_tolerance=1e-12,
                       max_substeps=10**7)
    dem = make_cell_model("dem", dim=3, settings=fine, threads=1)
    meso = tetrahedral_cell()
    n = 4
    rng = np.random.default_rng(2)
    state = dem.init_state(meso, n)
    direction = rng.normal(size=(n, 3))
    for k in range(20):
        state, _ = dem.step(state, np.full((n, 3), 1e-4) if k < 8 else 1e-4 * direction)
    d = 1e-6 * direction
    new, response = dem.step(state, d, with_tangent=True)
    before, after = state.dem.to_numpy(), new.dem.to_numpy()
    sliding = sliding_contacts_3d(before["position"], after["position"], state.model.radius.numpy(), meso.pairs,
                                  before["shear_force"], kn=dem.contact_law.kn, kt=dem.contact_law.kt,
                                  mu=dem.contact_law.mu)
    loaded = (after["contact"] == 1) & (np.linalg.norm(after["contact_force"], axis=-1) > 0.0)
    assert sliding.any() and (loaded & ~sliding).any()
    held = fd_tangent_fixed_schedule(dem, state, d, 0.1 * fine.strain_per_substep)
    error = relative_error(response.tangent, held)
    slides = sliding.any(axis=1)
    assert slides.any() and (~slides).any()
    assert error[~slides].max() < 1e-5, error
    assert error[slides].max() < 1e-3, error  # measured 4.8e-4 (4.0e-4 at 1e-9 per substep)


def test_hertz_mindlin_cells_count_contacts_stiffer_than_their_time_step():
    """The Hertz-Mindlin DEM sets its time step at an overlap of HERTZ_DT_OVERLAP (r_i + r_j); a cell with a
    larger overlap is counted in ``n_stiffer_than_dt`` (the linear law has no such count)."""
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    model = make_cell_model("dem", dim=3, contact_law=HertzMindlinLaw())
    state = model.init_state(meso, 1)
    counts, overlaps = [], []
    for _ in range(60):
        state, response = model.step(state, np.array([[1e-4, 0.0, 0.0]]))
        counts.append(response.diagnostics["n_stiffer_than_dt"])
        x = np.stack([[model.observables(state)[f"x_{a}{g}"][0] for a in ("n", "t1", "t2")] for g in range(1, 11)])
        gaps = np.linalg.norm(x[:, None] - x[None], axis=-1)[np.triu_indices(10, 1)] - 1.0
        overlaps.append(-gaps.min())
    expected = (np.array(overlaps) > HERTZ_DT_OVERLAP * 1.0).astype(float)
    np.testing.assert_array_equal(counts, expected)
    assert expected[0] == 0.0 and expected[-1] == 1.0
    linear = make_cell_model("dem", dim=3)
    _, response = linear.step(linear.init_state(meso, 1), np.array([[1e-4, 0.0, 0.0]]))
    assert "n_stiffer_than_dt" not in response.diagnostics
