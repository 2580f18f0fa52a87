"""Readers shared by the tests of the committed YADE references of 3D cells (``tests/data/yade3d*``):
the generating scripts (they run inside YADE, so they are loaded by path, not imported as modules of the
package) and one case's files."""

from __future__ import annotations

import importlib.util
import json
import sys
from itertools import combinations
from pathlib import Path

import numpy as np

YADE_SCRIPTS = Path(__file__).resolve().parent / "yade"
PAIRS = list(combinations(range(10), 2))
"""The ten-sphere cell's 45 grain pairs (i < j), in the order of the references' fn_I_J columns."""


def linear_normal_forces(position: np.ndarray, radius: float = 0.5, kn: float = 2e8) -> np.ndarray:
    """kn <2 r - |x_j - x_i|> of every pair of PAIRS (rows, 45) [N] from centres (rows, 10, 3) [m]."""
    i, j = np.array(PAIRS).T
    gap = np.linalg.norm(position[:, j] - position[:, i], axis=-1) - 2.0 * radius
    return kn * np.maximum(-gap, 0.0)


def yade_script(name: str):
    """The module of ``tests/yade/NAME.py``, loaded by path (its ``CASES`` and constants)."""
    spec = importlib.util.spec_from_file_location(name, YADE_SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def read_case(data_dir: Path, name: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """(cell description, imposed path rows, YADE's table) of case ``name`` in ``data_dir``."""
    cell = json.loads((data_dir / f"{name}.cell.json").read_text())
    path = np.loadtxt(data_dir / f"{name}.path.csv", delimiter=",", skiprows=1, ndmin=2)
    table = np.genfromtxt(data_dir / f"{name}.yade.csv", delimiter=",", names=True)
    return cell, path, table


def assert_regenerates(make_reference, data_dir: Path, name: str, tmp_path: Path) -> None:
    """Runs YADE on case ``name`` of the generating script ``make_reference`` into tmp_path and asserts that
    every column of its table equals the committed one in ``data_dir`` (rtol and atol 1e-9)."""
    prefix = make_reference.generate(name, tmp_path)
    fresh = np.genfromtxt(f"{prefix}.yade.csv", delimiter=",", names=True)
    committed = read_case(data_dir, name)[2]
    for column in committed.dtype.names:
        np.testing.assert_allclose(fresh[column], committed[column], rtol=1e-9, atol=1e-9, err_msg=column)


def assert_committed_cell(cell: dict, meso) -> None:
    """The committed cell description ``cell`` (``NAME.cell.json``) is the package's mesostructure ``meso``:
    the same grain centres and cell size (to 1e-15) and the same driven DOFs."""
    np.testing.assert_allclose(cell["position"], meso.position, atol=1e-15)
    np.testing.assert_array_equal(cell["driven"], meso.driven)
    np.testing.assert_allclose(cell["cell_size"], meso.cell_size, atol=1e-15)
