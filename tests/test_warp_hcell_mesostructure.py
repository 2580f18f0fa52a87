"""Mesostructures: the H-cell builder against spec section 2, the file loader, and bad descriptions."""

import json
import math
import tomllib
from importlib import resources

import numpy as np
import pytest

from warp_hcell.mesostructures.mesostructure import (
    Mesostructure,
    MesostructureError,
    per_cell,
    polygon_area,
    shares_state_schema,
)
from warp_hcell.mesostructures.files import describe, description_sha256, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import h_cell, reference as h_cell_reference

DATA = resources.files("warp_hcell") / "data"


@pytest.mark.parametrize("alpha0_deg", [30.0, 40.0, 55.0, 60.0, 89.0])
def test_h_cell_matches_spec_geometry(alpha0_deg):
    r = 0.5
    meso = h_cell(alpha0_deg, r)
    a = math.radians(alpha0_deg)
    x_n, x_t = meso.position[:, 0], meso.position[:, 1]
    # spec section 2, labels 1..6, coordinates (x_t, x_n) there, (x_n, x_t) here
    np.testing.assert_allclose(x_n, [0.5 + math.cos(a), 0.5, -0.5, -0.5 - math.cos(a), -0.5, 0.5], atol=1e-15)
    np.testing.assert_allclose(x_t, [0.0, -math.sin(a), -math.sin(a), 0.0, math.sin(a), math.sin(a)], atol=1e-15)
    np.testing.assert_allclose(meso.cell_size, [1.0 + 2.0 * math.cos(a), 2.0 * math.sin(a)], rtol=1e-15)
    # V_cell = l2 (d2 + d1 cos a) with d1 = d2 = D
    assert polygon_area(meso.position, meso.outer) == pytest.approx(2 * math.sin(a) * (1 + math.cos(a)), rel=1e-14)
    # grains 1, 4 driven along n and t; 2, 3, 5, 6 driven along t only
    assert meso.driven.tolist() == [[True, True], [False, True], [False, True],
                                    [True, True], [False, True], [False, True]]


def test_h_cell_labels_and_candidate_pairs():
    meso = h_cell(55.0, 0.5)
    assert meso.n_grains == 6 and meso.n_pairs == 15
    labelled = {(int(i) + 1, int(j) + 1): int(k) for (i, j), k in zip(meso.pairs, meso.pair_label) if k}
    assert labelled == {(1, 2): 1, (1, 6): 1, (3, 4): 1, (4, 5): 1, (2, 3): 2, (5, 6): 2}
    p12, p23 = meso.pair_index(0, 1), meso.pair_index(1, 2)
    assert meso.pairs[p12].tolist() == [0, 1] and meso.pairs[p23].tolist() == [1, 2]
    # the six labelled contacts are touching: d1 = d2 = D
    i, j = meso.pairs[meso.pair_label > 0].T
    np.testing.assert_allclose(np.linalg.norm(meso.position[j] - meso.position[i], axis=1), 1.0, rtol=1e-15)


def test_vectorised_reference_matches_builder():
    alphas = np.array([33.0, 47.5, 71.0])
    position, cell_size = h_cell_reference(alphas, 0.7)
    for k, a in enumerate(alphas):
        meso = h_cell(a, 0.7)
        assert np.array_equal(position[k], meso.position) and np.array_equal(cell_size[k], meso.cell_size)


def test_shipped_lateral_file_is_a_touching_h_cell():
    meso = load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")
    assert meso.parameters and meso.observables and meso.n_grains == 6
    np.testing.assert_array_equal(meso.radius, [0.5, 0.35, 0.35, 0.5, 0.35, 0.35])
    i, j = meso.pairs[meso.pair_label > 0].T
    gap = np.linalg.norm(meso.position[j] - meso.position[i], axis=1) - meso.radius[i] - meso.radius[j]
    np.testing.assert_allclose(gap, 0.0, atol=1e-12)
    a = math.radians(55.0)
    np.testing.assert_allclose(meso.cell_size, [0.7 + 2 * 0.85 * math.cos(a), 2 * 0.85 * math.sin(a)], rtol=1e-14)


def test_shipped_fine_grain_file_has_a_free_grain_in_the_pore():
    meso = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    assert meso.n_grains == 7 and meso.n_pairs == 21
    assert meso.driven[6].tolist() == [False, False]
    assert 6 not in meso.outer.tolist()
    gaps = [np.linalg.norm(meso.position[6] - meso.position[g]) - meso.radius[6] - meso.radius[g] for g in (1, 2, 4, 5)]
    np.testing.assert_allclose(gaps, 0.0, atol=1e-12)


def test_json_and_toml_describe_the_same_cell(tmp_path):
    source = DATA / "h_cell_lateral_0.7D.toml"
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(tomllib.loads(source.read_text())))
    a, b = load_mesostructure(source), load_mesostructure(path)
    for name in ("radius", "position", "driven", "pairs", "outer", "cell_size", "pair_label"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def _square(**changes):
    """Four equal grains at the corners of a unit square (neighbours touching), all DOFs driven."""
    description = dict(name="square", radius=[0.5] * 4, position=[[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]],
                       driven=[[True, True]] * 4, pairs=[[0, 1], [1, 2], [2, 3], [0, 3]], outer=[0, 1, 2, 3],
                       cell_size=[2.0, 2.0])
    description.update(changes)
    return Mesostructure(**{k: np.asarray(v) if k != "name" else v for k, v in description.items()})


@pytest.mark.parametrize("changes, message", [
    (dict(radius=[0.5, -0.1, 0.5, 0.5]),
     "mesostructure 'square': grain 2 has radius -0.1; radii must be finite and > 0"),
    (dict(radius=[0.5, 0.5, 0.0, 0.5]), "mesostructure 'square': grain 3 has radius 0; radii must be finite and > 0"),
    (dict(position=[[0.4, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]]),
     "mesostructure 'square': grains 1 and 2 overlap by 0.1 m (more than the contact tolerance)"),
    (dict(driven=[[True, True], [False, False], [True, True], [True, True]]),
     "mesostructure 'square': outer grain 2 has no driven DOF; outer grains follow the cell strain"),
    (dict(driven=[[1, 1]] * 4), "mesostructure 'square': driven flags must be booleans, shape (4, 2)"),
    (dict(pairs=[[1, 1]]), "mesostructure 'square': pairs must be (i, j) with 1 <= i < j <= 4"),
    (dict(pairs=[[0, 1], [0, 1]]), "mesostructure 'square': duplicate contact pairs"),
    (dict(pairs=[[0, 1], [1, 2], [2, 3]]), "mesostructure 'square': grains 1 and 4 touch but are not a candidate "
     "pair (their contact would carry no force): add [1, 4] to pairs"),
    (dict(outer=[0, 1, 1]), "mesostructure 'square': outer polygon needs >= 3 distinct grains in 1..4"),
    (dict(cell_size=[1.0, 0.0]), "mesostructure 'square': cell_size must be two finite values > 0"),
])
def test_invalid_descriptions_give_one_line_errors(changes, message):
    with pytest.raises(MesostructureError) as info:
        _square(**changes)
    assert str(info.value) == message


def test_overlap_within_tolerance_is_accepted():
    meso = _square(position=[[0.5 - 1e-12, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
    assert meso.n_pairs == 4 and not meso.observables and not meso.parameters


@pytest.mark.parametrize("old, new, match", [
    ("outer = [", "outer = [[", "is not valid TOML"),
    ("cell_size", "cellsize", "unknown key 'cellsize' at the top level of .*bad.toml \\(did you mean 'cell_size'\\?\\)"),
    ("radius = 0.35", "radius = 0.45", "grains 1 and 2 overlap by 0.1 m"),
    ("driven = [false, true]", 'driven = ["no", true]', r"each grain needs driven = \[bool, bool\]"),
])
def test_loader_errors(tmp_path, old, new, match):
    text = (DATA / "h_cell_lateral_0.7D.toml").read_text()
    assert old in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(MesostructureError, match=match):
        load_mesostructure(bad)


def test_loader_error_of_a_missing_file(tmp_path):
    with pytest.raises(MesostructureError, match="cannot read mesostructure file"):
        load_mesostructure(tmp_path / "absent.toml")
    assert issubclass(MesostructureError, ValueError)


def test_h_cell_rejects_inadmissible_alpha0():
    with pytest.raises(ValueError, match=r"alpha0 = 90 deg is outside \[30, 90\) deg"):
        h_cell(90.0, 0.5)


@pytest.mark.parametrize("name", ["h-cell", "h_cell_lateral_0.7D.toml", "h_cell_fine_grain.toml"])
def test_description_round_trip_and_hash(name):
    meso = h_cell(40.0) if name == "h-cell" else load_mesostructure(DATA / name)
    text = describe(meso)
    again = from_description(text)
    assert describe(again) == text and json.loads(text) == json.loads(json.dumps(json.loads(text), sort_keys=True))
    for field in ("radius", "position", "driven", "pairs", "outer", "cell_size", "pair_label"):
        np.testing.assert_array_equal(getattr(again, field), getattr(meso, field))
    assert again.observables == meso.observables and again.parameters == meso.parameters and again.contact_tolerance == meso.contact_tolerance
    assert len(description_sha256(text)) == 64
    assert description_sha256(describe(h_cell(40.0 + 1e-9))) != description_sha256(describe(h_cell(40.0)))


def test_from_description_errors_are_one_line():
    with pytest.raises(MesostructureError, match="not JSON"):
        from_description("{")
    with pytest.raises(MesostructureError, match="not a mesostructure description"):
        from_description('{"a": 1}')
    text = json.loads(describe(h_cell()))
    del text["outer"]
    with pytest.raises(MesostructureError, match="missing key 'outer'"):
        from_description(json.dumps(text))


def test_state_schema_of_the_fine_grain_cell():
    meso = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    schema = meso.schema()
    # grains 2, 3, 5, 6 free along n; the fine grain 7 free along n and t
    assert schema.free_dofs.tolist() == [[1, 0], [2, 0], [4, 0], [5, 0], [6, 0], [6, 1]]
    assert schema.features["free_position"].names == ("x_n2", "x_n3", "x_n5", "x_n6", "x_n7", "x_t7")
    assert schema.features["unbalanced"].names[-1] == "f_t7"
    assert schema.features["shear_force"].names[0] == "fs_1_2" and len(schema.features["contact"].names) == 21
    assert schema.of_role("learned") == ("free_position",)
    assert schema.of_role("history") == ("shear_force",)
    assert set(schema.of_role("derived")) == {"contact", "normal_force", "unbalanced", "moment", "area"}
    assert json.loads(schema.feature_json())["moment"]["unit"] == "N m"
    with pytest.raises(ValueError, match="role 'input'"):
        schema.of_role("input")


def test_h_cells_of_every_angle_share_one_learning_state():
    assert shares_state_schema(h_cell(55.0), h_cell(30.0)) and shares_state_schema(h_cell(55.0), h_cell(89.0))
    assert not shares_state_schema(h_cell(55.0), load_mesostructure(DATA / "h_cell_lateral_0.7D.toml"))
    assert not shares_state_schema(h_cell(55.0, 0.5), h_cell(55.0, 0.4))


def test_per_cell_groups_cells_by_their_mesostructure_object():
    a, b = h_cell(40.0), h_cell(55.0)
    distinct, index = per_cell([a, b, a, a, b], 5)
    assert distinct == (a, b) and index.tolist() == [0, 1, 0, 0, 1]
    distinct, index = per_cell(b, 3)
    assert distinct == (b,) and index.tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match=r"need one mesostructure or n_cells = 3 of them, got 2"):
        per_cell([a, b], 3)
    with pytest.raises(ValueError, match="cell 1: float is not a Mesostructure"):
        per_cell([a, 55.0], 2)
