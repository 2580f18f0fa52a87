"""YADE reference cases of the ten-sphere H-cell (tests/data/yade3d).

- The committed cell of every case is the package's ``hcell3d`` cell at the case's opening angle.
- The 3D DEM and the closed form driven through the CellModel protocol row by row along each
  case's path: every pair's normal force within 1e-3 of the case's largest force, and the grain
  centres within 1e-6 D wherever the cell carries force.
- Behind the ``yade`` marker (needs ``yade`` on PATH): regenerating a case reproduces the committed
  outputs.
"""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.builders import resolve_mesostructure
from yade_cases import PAIRS, assert_committed_cell, assert_regenerates, linear_normal_forces, read_case, yade_script

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE / "data" / "yade3d"
FORCE_RTOL = 1e-3
"""Contact forces: tolerance as a fraction of the case's largest force [-]."""
POSITION_TOL = 1e-6
"""Grain centres where the cell carries force [m] (1e-6 D)."""


MAKE_REFERENCE = yade_script("make_reference3d")
CASE_NAMES = tuple(MAKE_REFERENCE.CASES)


@functools.lru_cache(maxsize=None)
def _case(name: str) -> tuple[dict, np.ndarray, np.ndarray]:
    return read_case(DATA_DIR, name)



@pytest.mark.parametrize("name", CASE_NAMES)
def test_the_committed_cell_is_the_packages_ten_sphere_cell(name):
    cell = _case(name)[0]
    meso = resolve_mesostructure(f"hcell3d:alpha0={MAKE_REFERENCE.CASES[name].alpha0_deg}")
    assert_committed_cell(cell, meso)


@pytest.mark.parametrize("backend", ["dem", "analytical"])
@pytest.mark.parametrize("name", CASE_NAMES)
def test_backend_matches_yade_along_the_path(name, backend):
    cell, path, table = _case(name)
    meso = resolve_mesostructure(f"hcell3d:alpha0={MAKE_REFERENCE.CASES[name].alpha0_deg}")
    model = make_cell_model(backend, dim=3)
    state = model.init_state(meso, 1)
    yade_fn = np.stack([table[f"fn_{i + 1}_{j + 1}"] for i, j in PAIRS], axis=1)
    yade_x = np.stack([np.stack([table[f"x_{a}{g}"] for a in ("n", "t1", "t2")], axis=-1)
                       for g in range(1, 11)], axis=1)
    positions = []
    for d_eps in path:
        state, _ = model.step(state, d_eps[None])
        obs = model.observables(state)
        positions.append(np.stack([np.stack([obs[f"x_{a}{g}"][0] for a in ("n", "t1", "t2")]) for g in range(1, 11)]))
    positions = np.array(positions)
    scale = yade_fn.max()
    assert scale > 1e5
    assert np.abs(linear_normal_forces(positions) - yade_fn).max() <= FORCE_RTOL * scale
    loaded = yade_fn.max(axis=1) > 0.0
    assert loaded.mean() > 0.9
    assert np.abs(positions[loaded] - yade_x[loaded]).max() <= POSITION_TOL


@pytest.mark.yade
@pytest.mark.skipif(shutil.which("yade") is None, reason="needs yade on PATH")
@pytest.mark.parametrize("name", ["axial3d_a55"])
def test_regenerating_a_case_reproduces_the_committed_outputs(name, tmp_path):
    assert_regenerates(MAKE_REFERENCE, DATA_DIR, name, tmp_path)
