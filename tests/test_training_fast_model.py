"""The meso-ANN read without torch (``training.fast_model``), and the compiled ANN run that never imports torch (nor,
in 2D, numba)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections import OrderedDict

import numpy as np
import pytest
import torch

from homogenization.ann import default_model_path
from training.checkpoint import load_checkpoint
from training.fast_model import arrays_of_net, net_arrays, read_state_dict, StateDictError
from training.ood import BRUTE_FORCE_ROWS, OodIndex

MODELS = [default_model_path(2), default_model_path(3)]


@pytest.mark.parametrize("model", MODELS, ids=["2d", "3d"])
def test_the_state_dict_read_without_torch_is_torch_s(model):
    expected = torch.load(model, map_location="cpu", weights_only=True)
    got = read_state_dict(model)
    assert list(got) == list(expected)
    for key, tensor in expected.items():
        assert got[key].dtype == tensor.numpy().dtype, key
        np.testing.assert_array_equal(got[key], tensor.numpy(), err_msg=key)


def test_a_strided_and_offset_tensor_is_read_as_torch_reads_it(tmp_path):
    base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
    state = OrderedDict(t=base.t(), tail=base.reshape(-1)[5:], flag=torch.tensor([True, False]),
                        scalar=torch.tensor(3.5, dtype=torch.float64))
    torch.save(state, tmp_path / "m.pt")
    got = read_state_dict(tmp_path / "m.pt")
    for key, tensor in torch.load(tmp_path / "m.pt", weights_only=True).items():
        np.testing.assert_array_equal(got[key], tensor.numpy(), err_msg=key)


def test_a_file_holding_other_objects_than_tensors_is_refused(tmp_path):
    torch.save({"w": torch.zeros(2), "config": OrderedDict(a=1), "shape": torch.Size([2])}, tmp_path / "odd.pt")
    with pytest.raises(StateDictError, match="not only tensors"):
        read_state_dict(tmp_path / "odd.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a zip")
    with pytest.raises(StateDictError, match="not a readable"):
        read_state_dict(tmp_path / "junk.pt")


@pytest.mark.parametrize("model", MODELS, ids=["2d", "3d"])
def test_the_arrays_read_without_torch_are_those_of_the_torch_network(model):
    net, meta = load_checkpoint(model)
    got, expected = net_arrays(model, meta), arrays_of_net(net)
    for name in ("radius", "driven_fraction", "free_dofs", "pairs", "outer"):
        a, b = getattr(got.schema, name), getattr(expected.schema, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    for name in ("kn", "kt", "mu", "contact_tolerance", "diameter", "dim", "shear_shape"):
        assert getattr(got.schema, name) == getattr(expected.schema, name), name
    assert got.schema.diameter == net.schema.diameter and got.schema.shear_shape == tuple(net.schema.shear_shape)
    for name in ("active_index", "feature_mean", "feature_std", "rate_mean", "rate_std"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
    assert len(got.layers) == len(expected.layers) == len(net.hidden) + 1
    for (w, b), (w2, b2) in zip(got.layers, expected.layers):
        np.testing.assert_array_equal(w, w2)
        np.testing.assert_array_equal(b, b2)


@pytest.mark.parametrize("dim", [2, 3])
def test_an_ann_run_on_cpu_never_imports_torch_and_gives_the_torch_response(dim):
    """Steps, response and observables of the compiled path; the torch network gives the same response."""
    script = textwrap.dedent(f"""
        import sys, json
        import numpy as np
        from homogenization.backends import make_cell_model
        from warp_hcell.mesostructures.builders import resolve_mesostructure
        model = make_cell_model("ann", dim={dim})
        meso = resolve_mesostructure("{'hcell3d:alpha0=55' if dim == 3 else 'hcell:alpha0=55'}")
        state = model.init_state(meso, 5)
        for k in range(20):
            state, response = model.step(state, np.full((5, {dim}), 2e-5) * (1 + np.arange(5)[:, None]))
        out = model.response(state)
        obs = model.observables(state)
        print(json.dumps({{"torch": "torch" in sys.modules, "scipy.spatial": "scipy.spatial" in sys.modules,
                          "numba": "numba" in sys.modules,
                          "moment": np.asarray(out.moment).tolist(), "area": np.asarray(out.area).tolist(),
                          "step_moment": np.asarray(response.moment).tolist(), "n_contacts": obs["n_contacts"].tolist(),
                          "state": [np.asarray(a).tolist() for a in state]}}))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    import json  # noqa: PLC0415

    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert not got["torch"] and not got["scipy.spatial"]
    if got["numba"]:  # the first run on a machine builds the precompiled step with numba
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
        got = json.loads(done.stdout.strip().splitlines()[-1])
    assert not got["numba"]  # the fused step is precompiled (training.precompiled): no numba
    np.testing.assert_allclose(got["moment"], got["step_moment"], rtol=1e-12, atol=1e-9 * np.abs(got["moment"]).max())
    from homogenization.backends import make_cell_model  # noqa: PLC0415
    from training import cell_physics  # noqa: PLC0415

    model = make_cell_model("ann", dim=dim)
    size, free, shear = (torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in got["state"])
    x = cell_physics.positions(model.net.schema, size, free)
    c = cell_physics.contacts(model.net.schema, x)
    moment = cell_physics.love_weber(c, cell_physics.pair_forces(c, shear)).numpy()
    area = cell_physics.cell_measure(x, model.net.schema.outer).numpy()
    np.testing.assert_allclose(got["moment"], moment, rtol=1e-13, atol=1e-13 * np.abs(moment).max())
    np.testing.assert_allclose(got["area"], area, rtol=1e-14)
    np.testing.assert_array_equal(got["n_contacts"], c.contact.numpy().sum(axis=1))


def test_the_nearest_neighbour_distance_is_scipy_s():
    """Brute force (few rows) and the tree (many rows) equal a k-d tree to rounding, repeats, near ties and exact hits included."""
    from scipy.spatial import cKDTree  # noqa: PLC0415

    rng = np.random.default_rng(3)
    points = rng.normal(size=(500, 12))
    index = OodIndex(points, 1.0, 0.999, 1, "", "")
    queries = np.concatenate([rng.normal(size=(200, 12)), points[:30], points[:30] + 1e-10,
                              np.repeat(points[40:41] * 0.5, 7, axis=0), 1e3 + rng.normal(size=(5, 12))])
    expected = cKDTree(points).query(queries, k=1)[0]
    np.testing.assert_allclose(index._brute_force(queries), expected, rtol=1e-12, atol=1e-12)
    assert np.all(index._brute_force(points[:30]) == 0.0)
    np.testing.assert_allclose(index.distance(queries), expected, rtol=1e-12, atol=1e-12)
    few = np.concatenate([queries[:20], np.repeat(queries[:1], 300, axis=0)])
    assert np.unique(few, axis=0).shape[0] <= BRUTE_FORCE_ROWS
    np.testing.assert_allclose(index.distance(few), cKDTree(points).query(few, k=1)[0], rtol=1e-12, atol=1e-12)
