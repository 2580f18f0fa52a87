"""The compiled release test of the hybrid (``DemEscalation.released``) decides as the numpy operations of
``warp_hcell.database.learning_state`` (``positions``, ``pair_normal_forces``) do, bit for bit, also where a
pair's force ratio sits on the threshold. Oracle: those numpy functions, which the DEM's learning states use."""

from pathlib import Path

import numpy as np
import pytest

from homogenization.ann.escalation import DemEscalation
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.database.learning_state import pair_normal_forces, positions
from warp_hcell.mesostructures.builders import mesostructure_arg

ROOT = Path(__file__).resolve().parents[1]
CELLS = ROOT / "benchmarks" / "cells"


def _numpy_released(schema, law, tolerance, ratio, size, before, after, strict=True) -> np.ndarray:
    normal = pair_normal_forces(schema, positions(schema, size, after), law, tolerance)[3]
    threshold = ratio * normal.max(axis=1, keepdims=True)
    pressed = normal > threshold if strict else normal >= threshold
    n_grains = schema.radius.shape[0]
    touching = np.zeros((size.shape[0], n_grains), dtype=bool)
    for p, (i, j) in enumerate(schema.pairs):
        touching[:, i] |= pressed[:, p]
        touching[:, j] |= pressed[:, p]
    moved = np.zeros_like(touching)
    for k, (grain, _) in enumerate(schema.free_dofs):
        moved[:, grain] |= after[:, k] != before[:, k]
    return np.any(moved & ~touching, axis=1)


@pytest.mark.parametrize("cell", ["fine_off_centre.toml", "large_axial.toml"])
def test_the_compiled_release_test_is_the_numpy_one_bit_for_bit(cell):
    meso = mesostructure_arg(str(CELLS / cell)).build(None)
    schema, law = meso.schema(), ContactLaw()
    rng = np.random.default_rng(1)
    n = 1500
    size = meso.cell_size * (1.0 - rng.uniform(0.0, 2e-3, (n, 3)))
    start = meso.position[schema.free_dofs[:, 0], schema.free_dofs[:, 1]]
    before = np.tile(start, (n, 1))
    after = before + rng.normal(0.0, 2e-3, before.shape) * (rng.random(before.shape) < 0.5)  # some DOFs stay
    after[: n // 4] = before[: n // 4]  # nothing moved
    normal = pair_normal_forces(schema, positions(schema, size, after), law, meso.contact_tolerance)[3]
    largest = normal.max(axis=1)
    on_threshold = None
    candidates = []
    for grain in np.unique(schema.free_dofs[:, 0]):  # grains that moved and that one pair presses, ...
        grain_pairs = np.flatnonzero((schema.pairs == grain).any(axis=1))
        moved = (after != before)[:, schema.free_dofs[:, 0] == grain].any(axis=1)
        for c in np.flatnonzero(moved & ((normal[:, grain_pairs] > 0).sum(axis=1) == 1))[:20]:
            f = normal[c, grain_pairs].max()
            if f < largest[c] and (f / largest[c]) * largest[c] == f:  # ... at exactly the threshold
                candidates.append(float(f / largest[c]))
    for ratio in candidates:  # one where > and >= decide a cell differently
        args = (schema, law, meso.contact_tolerance, ratio, size, before, after)
        if not np.array_equal(_numpy_released(*args), _numpy_released(*args, strict=False)):
            on_threshold = ratio
            break
    assert on_threshold is not None
    decided = []
    for ratio in (1e-4, 1e-2, on_threshold):
        compiled = DemEscalation(meso, law, meso.contact_tolerance, force_ratio=ratio).released(size, before, after)
        expected = _numpy_released(schema, law, meso.contact_tolerance, ratio, size, before, after)
        np.testing.assert_array_equal(compiled, expected)
        decided.append(expected.sum())
    assert 0 < min(decided) and max(decided) < n  # both answers occur
