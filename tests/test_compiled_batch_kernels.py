"""The compiled loops that large 3D batches take (the tangent average, the cells' volume) give the bits of the
numpy expressions they replace, which stay in use below their thresholds."""

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.material import homogenised
from homogenization.material.homogenised import HomogenisedMaterial
from homogenization.material.orientation import orientations_3d
from homogenization.material.tangent_average import average
from warp_hcell.mesostructures import mesostructure
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.mesostructure import polyhedron_volume


@pytest.mark.parametrize("shape", [(1, 1), (2, 50), (3, 401)])
def test_the_compiled_tangent_average_is_the_two_einsums_bit_for_bit(shape):
    """Random tangents with exact zeros, negative zeros and entries 1e16 apart (rounding shows in any other order)."""
    n_points, n = shape
    rng = np.random.default_rng(n)
    C = rng.standard_normal((n_points, n, 3, 3)) * 10.0 ** rng.integers(-8, 8, (n_points, n, 3, 3))
    C[0, 0, 0] = -0.0
    C[-1, :, 1, 2] = 0.0
    L, A = rng.standard_normal((n, 3, 6)), rng.standard_normal((6, n, 3))
    out = np.full((n_points, 6, 6), np.nan)
    average(C, L, A, out)
    expected = np.einsum("ika,pkaj->pij", A, np.einsum("pkab,kbj->pkaj", C, L))
    assert out.tobytes() == expected.tobytes()
    if n > 1:  # the data tell orders apart: the orientations added backwards round otherwise
        backwards = np.einsum("ika,pkaj->pij", A[:, ::-1], np.einsum("pkab,kbj->pkaj", C[:, ::-1], L[::-1]))
        assert not np.array_equal(out, backwards)


def _loaded_tangent(monkeypatch, threshold):
    monkeypatch.setattr(homogenised, "COMPILED_TANGENT_FROM_CELLS", threshold)
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", threshold)
    material = HomogenisedMaterial(make_cell_model("analytical", dim=3), orientations_3d(5, 2),
                                   [resolve_mesostructure(f"hcell3d:alpha0={a}") for a in (52.0, 58.0)], 2)
    state = material.init_state()
    d_e = np.array([[6e-4, 4e-4, 5e-4, 0.0, 0.0, 0.0], [5e-4, 5e-4, 5e-4, 1e-4, 0.0, 0.0]])
    for _ in range(3):
        update = material.update(state, d_e, with_tangent=True)
        state = update.state
    return update


def test_a_3d_material_gives_the_same_bits_through_the_compiled_loops(monkeypatch):
    numpy_path = _loaded_tangent(monkeypatch, 10**9)
    compiled = _loaded_tangent(monkeypatch, 1)
    assert compiled.tangent.tobytes() == numpy_path.tangent.tobytes()
    assert compiled.stress.tobytes() == numpy_path.stress.tobytes()
    assert np.all(np.isfinite(compiled.tangent)) and np.abs(compiled.tangent).max() > 0.0


def test_the_compiled_volume_is_the_numpy_passes_bit_for_bit_and_the_cube_is_one(monkeypatch):
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    rng = np.random.default_rng(5)
    batch = meso.position[None, None] * rng.uniform(0.8, 1.2, (3, 29, 1, 3)) + rng.normal(0.0, 0.01, (3, 29, 10, 3))
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", 10**9)
    expected = polyhedron_volume(batch, meso.outer)
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", 1)
    compiled = polyhedron_volume(batch, meso.outer)
    assert compiled.shape == (3, 29) and compiled.tobytes() == expected.tobytes()
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    faces = [(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4), (2, 6, 7), (2, 7, 3), (0, 4, 6),
             (0, 6, 2), (1, 3, 7), (1, 7, 5)]
    np.testing.assert_allclose(polyhedron_volume(cube[None] + rng.normal(0.0, 5.0, (4, 1, 3)), np.array(faces)), 1.0,
                               rtol=1e-12)
