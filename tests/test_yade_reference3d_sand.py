"""YADE reference cases of the cell of ``hcell3d-sand`` on its own (amplified) path (tests/data/yade3d_sand).

- The committed cell is the kind's ten-sphere cell and every committed path is what the package's
  amplified kinematics hand to a cell along or normal to the loading axis on the undrained triaxial path
  (the gain-3 case: ``axisymmetric_map(3)``).
- The 3D DEM along each whole path, and the closed form until the lateral grains of the two planes meet
  (it leaves that contact out), driven through the CellModel protocol row by row: every pair's normal
  force within FORCE_RTOL of the case's largest and the Love-Weber moment within MOMENT_RTOL of its largest
  (before the planes meet: of the largest before), the grain centres within POSITION_TOL wherever a contact of the planes carries force.
- The references tell the gain: the DEM along the gain-1 path misses them; the closed form misses the
  moment once the planes meet.
- The case with decoupled planes (YADE body masks): the DEM of the cell without the pairs between the
  planes and the closed form follow it along the whole path, where the planes' grains overlap unloaded.
- Behind the ``yade`` marker: regenerating a case reproduces the committed outputs.
"""

from __future__ import annotations

import dataclasses
import functools
import shutil
from pathlib import Path

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.material.orientation import axisymmetric_map, localise, orientations_3d
from warp_hcell.mesostructures.builders import resolve_mesostructure
from yade_cases import PAIRS, assert_committed_cell, assert_regenerates, linear_normal_forces, read_case, yade_script

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE / "data" / "yade3d_sand"
FORCE_RTOL = 1e-3
"""Contact forces: tolerance as a fraction of the largest force [-]. Measured (largest over the cases,
rows 15-18 where the type-1 contacts start sliding): DEM 6.5e-4, closed form 2.8e-5."""
MOMENT_RTOL = {"dem": 2e-3, "analytical": 1e-3}
"""Love-Weber moment: tolerance as a fraction of the largest [-] (it sums the errors of several pairs;
measured DEM 1.13e-3, closed form 4.5e-5)."""
POSITION_TOL = 1e-6
"""Grain centres where a contact of the planes carries force [m] (1e-6 D; measured 3.9e-7 and 1.6e-8)."""

MAKE_REFERENCE = yade_script("make_reference3d_sand")
CASE_NAMES = tuple(MAKE_REFERENCE.CASES)
CROSS = np.array([(i in (1, 2, 4, 5)) and (j in (6, 7, 8, 9)) for i, j in PAIRS])
"""Pairs of a lateral grain of plane A (2, 3, 5, 6) and one of plane B (7-10)."""
MOMENT = ("S_nn", "S_t1t1", "S_t2t2")


@functools.lru_cache(maxsize=None)
def _case(name: str) -> tuple[dict, np.ndarray, np.ndarray]:
    return read_case(DATA_DIR, name)



def _yade(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(normal forces (rows, 45) [N], centres (rows, 10, 3) [m], moment diagonal (rows, 3) [N m])."""
    table = _case(name)[2]
    fn = np.stack([table[f"fn_{i + 1}_{j + 1}"] for i, j in PAIRS], axis=1)
    x = np.stack([np.stack([table[f"x_{a}{g}"] for a in ("n", "t1", "t2")], axis=-1) for g in range(1, 11)], axis=1)
    return fn, x, np.stack([table[c] for c in MOMENT], axis=1)


def _planes_meet(name: str) -> int:
    """First row where YADE has a force between the two planes' lateral grains (the row count if none)."""
    rows = np.flatnonzero(_yade(name)[0][:, CROSS].max(axis=1) > 0.0)
    return int(rows[0]) if rows.size else len(_case(name)[1])


def _decoupled(meso):
    """``meso`` without the candidate pairs between the two planes' lateral grains."""
    keep = ~CROSS[[PAIRS.index((int(i), int(j))) for i, j in meso.pairs]]
    return dataclasses.replace(meso, pairs=meso.pairs[keep], pair_label=meso.pair_label[keep])


def _drive(backend: str, name: str, path: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (rows, 10, 3), moment diagonal (rows, 3), cross-plane flag (rows,)) of ``backend`` along ``path``
    (the DEM of a decoupled case: the cell without the pairs between the planes)."""
    meso = resolve_mesostructure(f"hcell3d-sand:alpha0={MAKE_REFERENCE.CASES[name].alpha0_deg:g}")
    if MAKE_REFERENCE.CASES[name].apart and backend == "dem":
        meso = _decoupled(meso)
    model = make_cell_model(backend, dim=3)
    state = model.init_state(meso, 1)
    positions, moments, cross = [], [], []
    for d_eps in path:
        state, response = model.step(state, d_eps[None])
        obs = model.observables(state)
        positions.append(np.stack([np.stack([obs[f"x_{a}{g}"][0] for a in ("n", "t1", "t2")]) for g in range(1, 11)]))
        moments.append(np.diag(response.moment[0]))
        cross.append(bool(obs["cross_plane"][0]) if "cross_plane" in obs else False)
    return np.array(positions), np.array(moments), np.array(cross)


@pytest.mark.parametrize("name", CASE_NAMES)
def test_the_committed_cell_is_the_cell_of_hcell3d_sand(name):
    cell = _case(name)[0]
    meso = resolve_mesostructure(f"hcell3d-sand:alpha0={MAKE_REFERENCE.CASES[name].alpha0_deg:g}")
    assert_committed_cell(cell, meso)
    mask = np.array(cell.get("mask", [1] * 10))
    interacting = {(i, j) for i, j in PAIRS if mask[i] & mask[j]}
    expected = _decoupled(meso) if MAKE_REFERENCE.CASES[name].apart else meso
    assert interacting == set(map(tuple, expected.pairs.tolist()))


@pytest.mark.parametrize("name", CASE_NAMES)
def test_the_committed_path_is_the_amplified_kinematics_of_the_undrained_path(name):
    """The cell of an orientation set of the kind's kinematics whose axis is e1 ("axial") or e2 ("normal")
    takes the committed rows from the undrained macro increment (axial 2e-4, isochoric); the gain-3 case
    is the same cell strains through ``axisymmetric_map(3)``."""
    case = MAKE_REFERENCE.CASES[name]
    path = _case(name)[1]
    axial, lateral, _ = MAKE_REFERENCE.isochoric(MAKE_REFERENCE.MACRO_STEP)
    d_eps = np.array([axial, lateral, lateral, 0.0, 0.0, 0.0])
    meso = resolve_mesostructure(f"hcell3d-sand:alpha0={case.alpha0_deg:g}")
    orient = orientations_3d(11, 1, kinematics="amplified")
    assert meso.parameters["axisymmetric_kinematics"] == MAKE_REFERENCE.GAIN
    k = int(np.argmax(orient.axes[:, 0 if case.axis == "axial" else 1]))
    cell_strain = localise(orient, d_eps)[k]
    if case.gain != 2.0:
        projected = localise(orientations_3d(11, 1), d_eps)[k]
        cell_strain = axisymmetric_map(case.gain) @ np.array([projected[0], *[projected[1:].mean()] * 2])
    np.testing.assert_allclose(path[10:], np.tile(cell_strain, (len(path) - 10, 1)), rtol=1e-12, atol=1e-19)
    np.testing.assert_array_equal(path[:10], 1e-4)


@pytest.mark.parametrize("backend", ["dem", "analytical"])
@pytest.mark.parametrize("name", CASE_NAMES)
def test_backend_matches_yade_along_the_path(name, backend):
    """DEM: the whole path, the jam of the planes included; closed form: until the planes meet."""
    path = _case(name)[1]
    yade_fn, yade_x, yade_moment = _yade(name)
    positions, moments, cross = _drive(backend, name, path)
    meet = _planes_meet(name)
    forces = linear_normal_forces(positions)
    if MAKE_REFERENCE.CASES[name].apart:  # the overlaps between the planes carry no force in that cell
        forces[:, CROSS] = 0.0
    spans = [slice(0, meet)] + ([slice(0, len(path))] if backend == "dem" else [])
    for span in spans:
        scale = yade_fn[span].max()
        assert scale > 1e5
        assert np.abs(forces[span] - yade_fn[span]).max() <= FORCE_RTOL * scale
        assert np.abs(moments[span] - yade_moment[span]).max() <= MOMENT_RTOL[backend] * np.abs(yade_moment[span]).max()
    in_plane = yade_fn[:, ~CROSS].max(axis=1) > 0.0
    assert in_plane.sum() > 40  # rows with a contact of the planes (the closing cells open from row 54 or 75)
    assert np.abs(positions[in_plane] - yade_x[in_plane]).max() <= POSITION_TOL
    if backend == "analytical" and not MAKE_REFERENCE.CASES[name].apart:  # flags the contact it leaves out
        first = np.flatnonzero(cross)
        assert (first.size == 0) == (meet == len(path))
        assert first.size == 0 or abs(int(first[0]) - meet) <= 1


def test_with_decoupled_planes_the_grains_of_the_two_planes_overlap_without_force():
    """In the decoupled case YADE's planes overlap (centres closer than D from row 418, the row where the
    built cell's closed form would flag them) and carry no force between them, as the closed form assumes."""
    name = "sand3d_apart_g35_a52_normal"
    fn, x, _ = _yade(name)
    i, j = np.array(PAIRS).T
    distance = np.linalg.norm(x[:, j] - x[:, i], axis=-1)[:, CROSS]
    assert distance[-1].min() < 1.0 - 5e-3 and fn[:, CROSS].max() == 0.0
    cross = _drive("analytical", name, _case(name)[1])[2]
    overlap = np.flatnonzero(distance.min(axis=1) < 1.0)
    assert abs(int(np.flatnonzero(cross)[0]) - int(overlap[0])) <= 1


@pytest.mark.parametrize("name", ["sand3d_a49_normal", "sand3d_g3_a52_normal"])
def test_where_the_planes_meet_they_jam_and_the_closed_form_misses_it(name):
    """Once the lateral grains of the two planes touch, YADE's largest force grows at least fivefold
    (both grains are driven across the contact normal) and the DEM follows it; the closed form's moment
    leaves it out."""
    path = _case(name)[1]
    yade_fn, _, yade_moment = _yade(name)
    meet = _planes_meet(name)
    assert meet < len(path) and yade_fn[meet:, CROSS].max() > 5.0 * yade_fn[:meet].max()
    _, closed, _ = _drive("analytical", name, path)
    assert np.abs(closed - yade_moment).max() > 0.5 * np.abs(yade_moment).max()


def test_the_references_tell_the_gain():
    """The DEM along the gain-1 map of the same macro rows (hcell3d-axisym's) misses a gain-2 reference by
    more than ten times the tolerance."""
    name = "sand3d_a54_normal"
    case = MAKE_REFERENCE.CASES[name]
    path = _case(name)[1].copy()
    path[10:] = MAKE_REFERENCE.amplified(case.macro_step(), 1.0)
    yade_fn = _yade(name)[0]
    positions = _drive("dem", name, path)[0]
    assert np.abs(linear_normal_forces(positions) - yade_fn).max() > 10.0 * FORCE_RTOL * yade_fn.max()


@pytest.mark.yade
@pytest.mark.skipif(shutil.which("yade") is None, reason="needs yade on PATH")
def test_regenerating_a_case_reproduces_the_committed_outputs(tmp_path):
    name = "sand3d_a54_axial"
    assert_regenerates(MAKE_REFERENCE, DATA_DIR, name, tmp_path)
