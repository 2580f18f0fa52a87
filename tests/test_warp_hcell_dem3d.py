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
from homogenization.backends import make_cell_model
from warp_hcell.core.parameters import ContactLaw, DemSettings
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
