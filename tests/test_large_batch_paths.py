"""The paths that large batches take (the compiled tangent average and cell volume, the closed form's equilibrium
iteration narrowed to its unconverged cells) give the bits of the code that smaller batches run; the compiled
loops' tests are marked ``determinism`` (make determinism: under every CPU-feature setting of numpy and numba)."""

import numpy as np
import pytest

from homogenization.backends import analytical, make_cell_model
from homogenization.backends.analytical import Analytical3DCell, AnalyticalCell
from homogenization.material import homogenised
from homogenization.material.homogenised import HomogenisedMaterial
from homogenization.material.orientation import orientations_3d
from homogenization.material.tangent_average import average
from warp_hcell.mesostructures import mesostructure
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.mesostructure import polyhedron_volume


@pytest.mark.determinism
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


@pytest.mark.determinism
def test_a_3d_material_gives_the_same_bits_through_the_compiled_loops(monkeypatch):
    numpy_path = _loaded_tangent(monkeypatch, 10**9)
    compiled = _loaded_tangent(monkeypatch, 1)
    assert compiled.tangent.tobytes() == numpy_path.tangent.tobytes()
    assert compiled.stress.tobytes() == numpy_path.stress.tobytes()
    assert np.all(np.isfinite(compiled.tangent)) and np.abs(compiled.tangent).max() > 0.0


@pytest.mark.determinism
def test_the_compiled_volume_is_the_numpy_passes_bit_for_bit(monkeypatch):
    """Batch shape (3, 29); the unit cube through both paths: tests/test_warp_hcell_mesostructure3d.py."""
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    rng = np.random.default_rng(5)
    batch = meso.position[None, None] * rng.uniform(0.8, 1.2, (3, 29, 1, 3)) + rng.normal(0.0, 0.01, (3, 29, 10, 3))
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", 10**9)
    expected = polyhedron_volume(batch, meso.outer)
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", 1)
    compiled = polyhedron_volume(batch, meso.outer)
    assert compiled.shape == (3, 29) and compiled.tobytes() == expected.tobytes()


def _population(kind, n, rng):
    """A closed-form backend whose n cells have their own laws and opening angles."""
    alpha0 = rng.uniform(47.0, 62.0, n)
    if kind == "hertz":
        return Analytical3DCell.with_hertz_cell_laws(rng.uniform(5e9, 40e9, n), rng.uniform(0.1, 0.3, n),
                                                      rng.uniform(15.0, 35.0, n), 0.5, alpha0_deg=alpha0)
    cls = AnalyticalCell if kind == "planar" else Analytical3DCell
    return cls.with_cell_laws(rng.uniform(1e7, 1e8, n), rng.uniform(0.3, 1.5, n), rng.uniform(15.0, 35.0, n), 0.5,
                              alpha0_deg=alpha0)


def _run(kind, threshold, monkeypatch):
    """Compression, then shear and unloading of 400 cells with random local strains: (states' fields, tangents,
    diagnostics, the narrowings that fired)."""
    monkeypatch.setattr(analytical, "NARROW_FROM_CELLS", threshold)
    fired = []
    narrowed = AnalyticalCell._narrowed
    monkeypatch.setattr(AnalyticalCell, "_narrowed", lambda self, *a: fired.append(1) or narrowed(self, *a))
    rng = np.random.default_rng(11)
    n = 400
    model = _population(kind, n, rng)
    state = model.touching_state(model.cell_alpha0_deg, n)
    fields, tangents, diagnostics = [], [], []
    for k in range(60):
        d = np.full((n, model.dim), 2e-4) if k < 20 else rng.normal(0.0, 3e-4, (n, model.dim)) + (1e-4 if k < 45 else -2e-4)
        state, response = model.step(state, d, with_tangent=k % 7 == 0)
        fields.append(np.concatenate([np.concatenate(plane) for plane in model.layout.planes(state)]))
        tangents.append(response.tangent)
        diagnostics.append(response.diagnostics)
    return fields, tangents, diagnostics, len(fired)


@pytest.mark.parametrize("kind", ["planar", "spatial", "hertz"])
def test_the_narrowed_equilibrium_iteration_gives_the_whole_batchs_bits(kind, monkeypatch):
    whole = _run(kind, 10**9, monkeypatch)
    narrowed = _run(kind, 1, monkeypatch)
    assert whole[3] == 0 and narrowed[3] > 10  # the narrowing fired (and never without it)
    for a, b in zip(whole[0], narrowed[0]):
        assert a.tobytes() == b.tobytes()
    for a, b in zip(whole[1], narrowed[1]):
        assert (a is None and b is None) or a.tobytes() == b.tobytes()
    assert whole[2] == narrowed[2]
