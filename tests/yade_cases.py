"""Readers shared by the tests of the committed YADE references of 3D cells (``tests/data/yade3d*``):
the generating scripts (they run inside YADE, so they are loaded by path, not imported as modules of the
package) and one case's files."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

YADE_SCRIPTS = Path(__file__).resolve().parent / "yade"


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
