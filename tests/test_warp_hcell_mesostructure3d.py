"""3D mesostructures: the ten-sphere H-cell builder, its validation, files and descriptions."""

import math

import numpy as np
import pytest

from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.files import describe, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import build_h_cell_3d
from warp_hcell.mesostructures.hcell import plain_alpha0_3d as plain_h_cell_3d_alpha0
from warp_hcell.mesostructures import mesostructure
from warp_hcell.mesostructures.mesostructure import MesostructureError, cell_measure, polyhedron_volume


@pytest.mark.parametrize("alpha0", [46.0, 55.0, 80.0])
def test_every_labelled_contact_touches_and_nothing_else_does(alpha0):
    meso = resolve_mesostructure(f"hcell3d:alpha0={alpha0}")
    assert meso.dim == 3 and meso.n_grains == 10 and meso.n_pairs == 45
    branch = meso.position[meso.pairs[:, 1]] - meso.position[meso.pairs[:, 0]]
    gap = np.linalg.norm(branch, axis=1) - meso.radius[meso.pairs].sum(axis=1)
    labelled = meso.pair_label > 0
    assert labelled.sum() == 12
    np.testing.assert_allclose(gap[labelled], 0.0, atol=1e-12)
    assert np.all(gap[~labelled] > 1e-3)
    assert np.array_equal(meso.driven[[0, 3]], np.ones((2, 3), bool))
    assert np.array_equal(meso.driven[[1, 2, 4, 5, 6, 7, 8, 9]], np.tile([False, True, True], (8, 1)))
    a = math.radians(alpha0)
    np.testing.assert_allclose(meso.cell_size, [1 + 2 * math.cos(a), 2 * math.sin(a), 2 * math.sin(a)])


def test_the_volume_is_the_polyhedron_through_the_ten_centres():
    """Eight times the octant: the solid under the triangle (1, 6, 10) and the trapezoid (6, 10, 9, 5)
    down to n = 0, computed here by splitting it into three tetrahedra and a prism of the octant."""
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    a = math.radians(55.0)
    h, y, s = 0.5 + math.cos(a), 0.5, math.sin(a)
    # octant piece: pyramid-like top (apex T=(h,0,0) over the quarter square base at n = y) plus the
    # slab n in [0, y] of the right-triangle prism of legs s, s
    top = (h - y) * (0.5 * s * s) / 3.0
    slab = y * 0.5 * s * s
    assert float(cell_measure(meso.position, meso.outer)) == pytest.approx(8 * (top + slab), rel=1e-12)


@pytest.mark.parametrize("compiled_from", [10**9, 1], ids=["numpy", "compiled"])
def test_a_cells_volume_is_the_same_bits_alone_and_in_a_batch_and_the_shuffled_cube_is_one(compiled_from, monkeypatch):
    """The volume is summed face by face (``polyhedron_volume_of_rows``, its numpy passes or its compiled loop): a
    cell's value does not depend on the other cells of its batch; the unit cube through its 12 outward triangles has
    volume 1 wherever it sits."""
    monkeypatch.setattr(mesostructure, "COMPILED_VOLUME_FROM_CELLS", compiled_from)
    meso = resolve_mesostructure("hcell3d:alpha0=55")
    rng = np.random.default_rng(3)
    batch = meso.position[None] * rng.uniform(0.8, 1.2, (37, 1, 3)) + rng.normal(0.0, 0.01, (37, 10, 3))
    together = polyhedron_volume(batch, meso.outer)
    alone = np.array([polyhedron_volume(batch[i], meso.outer) for i in range(37)])
    assert np.array_equal(together, alone) and together.shape == (37,)
    np.testing.assert_array_equal(polyhedron_volume(batch.reshape(1, 37, 10, 3), meso.outer), together[None])
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    faces = [(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4), (2, 6, 7), (2, 7, 3), (0, 4, 6),
             (0, 6, 2), (1, 3, 7), (1, 7, 5)]
    shifted = cube[None] + rng.normal(0.0, 5.0, (4, 1, 3))
    np.testing.assert_allclose(polyhedron_volume(shifted, np.array(faces)), 1.0, rtol=1e-12)


def test_equal_spheres_below_45_degrees_overlap_across_the_planes():
    with pytest.raises(MesostructureError, match="lateral grains of the two planes overlap"):
        resolve_mesostructure("hcell3d:alpha0=40")
    assert resolve_mesostructure("hcell3d:alpha0=40,lateral=0.8").n_grains == 10


def test_fines_must_sit_inside_the_pore_and_fit():
    fines = resolve_mesostructure("hcell3d-fines:alpha0=55,ratio=0.3/0.3,n=0.45/-0.45,t1=0.1")
    assert fines.n_grains == 12 and not fines.driven[10:].any()
    with pytest.raises(MesostructureError, match="outside the pore"):
        resolve_mesostructure("hcell3d-fines:ratio=0.1,n=3")
    with pytest.raises(MesostructureError, match="does not fit"):
        resolve_mesostructure("hcell3d-fines:ratio=0.95")


def test_the_plain_cell_is_recognised_and_variants_are_not():
    assert plain_h_cell_3d_alpha0(resolve_mesostructure("hcell3d:alpha0=57.5")) == (57.5, 0.5)
    for spec in ("hcell3d:alpha0=57.5,plane=80", "hcell3d:lateral=0.9", "hcell3d-fines:ratio=0.3", "hcell:alpha0=57.5"):
        assert plain_h_cell_3d_alpha0(resolve_mesostructure(spec)) is None


def test_description_round_trip_and_file(tmp_path):
    meso = build_h_cell_3d(60.0, plane_angle_deg=80.0)
    again = from_description(describe(meso))
    for name in ("radius", "position", "driven", "pairs", "outer", "cell_size", "pair_label"):
        assert np.array_equal(getattr(again, name), getattr(meso, name))
    grains = "\n".join(f"[[grains]]\nradius = {float(r)!r}\nposition = {list(map(float, x))}\n"
                       f"driven = {[bool(v) for v in d]}".replace("True", "true").replace("False", "false")
                       for r, x, d in zip(meso.radius, meso.position, meso.driven))
    text = (f"name = 'cell'\ncell_size = {list(map(float, meso.cell_size))}\nouter = {(meso.outer + 1).tolist()}\n"
            + grains)
    (tmp_path / "cell.toml").write_text(text)
    loaded = load_mesostructure(tmp_path / "cell.toml")
    assert loaded.dim == 3 and np.array_equal(loaded.outer, meso.outer)
    np.testing.assert_array_equal(loaded.position, meso.position)
    (tmp_path / "bad.toml").write_text(text.replace("driven = [false, true, true]", "driven = [false, true]", 1))
    with pytest.raises(MesostructureError, match=r"driven = \[bool, bool, bool\] \(n, t1, t2\)"):
        load_mesostructure(tmp_path / "bad.toml")
