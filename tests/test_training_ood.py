"""Out-of-distribution index (training.ood) and its counts in the ANN backend."""

import shutil
import warnings

import numpy as np
import pytest
import torch

from homogenization.element_test import driver, programme as programmes
from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell
from training import ood
from training.checkpoint import load_checkpoint
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.hcell import h_cell

pytestmark = pytest.mark.skipif(not ood.index_path(default_model_path()).is_file(), reason="shipped index not installed")
LAW = ContactLaw()


def _counts(record: driver.Record) -> tuple[np.ndarray, np.ndarray]:
    checked = record.diagnostics["n_ood_checked"]
    return record.diagnostics["n_ood"][checked > 0], checked[checked > 0]


def test_a_biaxial_test_inside_the_database_has_no_outlier():
    cell = AnnCell(LAW, 0.5, ood_interval=50)
    record = driver.run(cell, programmes.biaxial(2e5, 0.05, 1e-4, iso_increment=1e-4), mesostructure=h_cell(55.0),
                        n_orientations=24, progress=False)
    outside, checked = _counts(record)
    assert checked.size == len(range(0, record.n_increments, 50)) and np.all(checked == 24)
    assert outside.sum() == 0 and tuple(cell.ood_counts) == (0, checked.sum())


def test_states_far_from_the_database_are_counted_and_warned_once():
    cell = AnnCell(LAW, 0.5, ood_interval=1)
    state = cell.init_state(h_cell(55.0), 8)
    far = state._replace(shear_force=np.full_like(state.shear_force, 50.0 * LAW.kn * 1.0),
                         free_position=state.free_position * 0.8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            far, response = cell.step(far, np.full((8, 2), 1e-4))
    assert response.diagnostics["n_ood"] == 8 and response.diagnostics["n_ood_checked"] == 8
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "out-of-distribution threshold" in messages[0] and "\n" not in messages[0]


def test_trials_from_one_state_are_checked_once():
    cell = AnnCell(LAW, 0.5, ood_interval=1)
    state = cell.init_state(h_cell(55.0), 4)
    for _ in range(3):  # stress-control trials: the same start state
        _, response = cell.step(state, np.full((4, 2), 1e-4))
        assert response.diagnostics["n_ood_checked"] == 4
    assert cell.ood_counts[1] == 4


def test_tree_distances_are_the_brute_force_nearest_neighbour_and_the_file_round_trips(tmp_path):
    net, _ = load_checkpoint(default_model_path())
    shipped = ood.load_index(ood.index_path(default_model_path()), net)
    assert shipped.points.shape == (ood.N_POINTS, net.feature_mean.shape[0] - ood.PROBE_COLUMNS)
    rng = np.random.default_rng(1)
    query = shipped.points[:300] + 0.3 * rng.standard_normal((300, shipped.points.shape[1]))
    brute = np.sqrt(((query[:, None, :] - shipped.points[None]) ** 2).sum(axis=2)).min(axis=1)
    np.testing.assert_allclose(shipped.distance(query), brute, rtol=1e-12)
    assert np.array_equal(shipped.outside(query), brute > shipped.threshold)
    back = ood.load_index(shipped.save(tmp_path / "i.npz"), net)
    assert back.threshold == shipped.threshold and np.array_equal(back.points, shipped.points)


def test_an_index_of_another_model_is_refused(tmp_path):
    folder = tmp_path / "m"
    folder.mkdir()
    source = default_model_path()
    for suffix in (".pt", ".json"):
        shutil.copy(source.with_suffix(suffix), folder / f"m{suffix}")
    shutil.copy(ood.index_path(source), ood.index_path(folder / "m.pt"))
    state = torch.load(folder / "m.pt", weights_only=True)
    state["feature_mean"] = state["feature_mean"] + 1e-3
    torch.save(state, folder / "m.pt")
    net, _ = load_checkpoint(folder / "m.pt")
    with pytest.raises(ood.OodError, match="another model"):
        ood.load_index(ood.index_path(folder / "m.pt"), net)
    with pytest.warns(RuntimeWarning, match="out-of-distribution checks are off"):
        cell = AnnCell(LAW, 0.5, model=folder / "m.pt")
    assert cell.ood is None
