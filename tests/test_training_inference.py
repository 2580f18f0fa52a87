"""Fast inference path (``training.inference.FastAdvance``) against the autograd path ``MesoNet.advance``.

Uses the shipped default model on loaded H-cells, including cells with capped tangential forces,
zero and tiny probes (relaxation ramp); and the DEM's rest rule in both paths on fines cells
with randomly initialised networks (whatever the network outputs, a force-free grain that
nothing reaches does not move). Tolerances are relative to the largest value of each
output: the tangential force, kt times a difference of nearly equal branch vectors, carries
rounding of ~1e-11 of it in float64.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fast_vs_torch import assert_fast_matches_torch
from other_cpus import OTHER_CPUS, planar_loaded
from training.cell_physics import CellSchema
from training.inference import FastAdvance, FastIncrement
from training.perceptron import BLOCK as MLP_BLOCK
from training.network import MesoNet
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.core.parameters import ContactLaw

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def loaded():
    return planar_loaded()


def _reference(cell, state, d):
    with torch.inference_mode():
        return cell.net.advance(*(torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in state),
                                torch.from_numpy(d))


def test_fast_increment_equals_the_autograd_path(loaded):
    """The float32 hidden layers round the rates and compliances to ~1e-7; the rest is float64."""
    cell, state, d = loaded
    ref = _reference(cell, state, d)
    fast = FastAdvance(cell.net)(*state, d)
    assert_fast_matches_torch(fast, ref, cell.net, d, ("cell_size", "free_position", "shear_force", "moment", "area"), 1e-6)


def test_a_cells_increment_is_bit_identical_in_any_batch_at_any_place(loaded):
    """Batches below, at and above whole perceptron blocks, the cell first, last or inside."""
    cell, state, d = loaded
    fast = FastAdvance(cell.net)
    rng = np.random.default_rng(2)
    whole = fast(*state, d)
    for n in (1, 7, MLP_BLOCK, MLP_BLOCK + 1, 3 * MLP_BLOCK - 5):
        index = rng.integers(0, d.shape[0], size=n)
        index[-1] = 5
        part = fast(*(np.asarray(a)[index] for a in state), d[index])
        for name in FastIncrement._fields:
            np.testing.assert_array_equal(getattr(part, name), getattr(whole, name)[index], err_msg=f"{name}, {n} cells")


def test_the_planar_increment_in_one_call_equals_its_kernels_apart(loaded):
    """``training.fast_increment.step`` (features, perceptron, advance and branch counts in one compiled call)
    gives the bits of the kernels called one after the other; its counts are those of the flags."""
    from training.fast_tables import Advanced, Before  # noqa: PLC0415
    from training.fast_features import features  # noqa: PLC0415
    from training.fast_increment import advance, step  # noqa: PLC0415
    from training.perceptron import forward_layers  # noqa: PLC0415

    cell, state, d = loaded
    fast = FastAdvance(cell.net)
    size, free, shear = (np.ascontiguousarray(np.moveaxis(np.asarray(a, dtype=np.float64), 0, -1)) for a in state)
    d = np.ascontiguousarray(d)
    n, n_free, weights, biases = size.shape[1], free.shape[0], fast.perceptron.weight, fast.perceptron.bias
    tables = (fast.cells, fast.law, fast.scaling)

    def scratch():
        before = Before(*(np.zeros_like(a) for a in fast._workspace(n).before))
        result = Advanced(np.zeros((2, n)), np.zeros((n_free, n)), np.zeros(shear.shape), np.zeros((n, 2, 2)),
                          np.zeros(n), *np.zeros((4, n), dtype=bool), np.zeros(n, dtype=np.int64),
                          np.zeros((n_free, n), dtype=bool))
        return before, fast.perceptron.padded_buffers(n), result

    one, apart = scratch(), scratch()
    counts = np.full(5, -1, dtype=np.int64)
    step(size, free, shear, d, *tables, weights, biases, *one, counts)
    features(size, free, shear, d, *tables, apart[0])
    forward_layers(weights, biases, apart[0].feats, apart[1])
    advance(size, free, shear, d, apart[1][-1], *tables, apart[0], apart[2])
    for x, y in zip([*one[0], *one[1], *one[2]], [*apart[0], *apart[1], *apart[2]]):
        np.testing.assert_array_equal(x, y)
    result = one[2]
    assert result.capped.any() and result.ramped.any()  # loaded and tiny-probe cells: counts that can be wrong
    expected = [np.count_nonzero(result.capped), np.count_nonzero(result.opened), np.count_nonzero(result.mechanism),
                np.count_nonzero(result.ramped), result.n_held.sum()]
    np.testing.assert_array_equal(counts, expected)


def test_later_calls_with_other_array_types_give_the_same_increment(loaded):
    """The kernels run the machine code of the first call's argument types: later inputs that are
    read-only, strided or float32 are converted to those types, and wrong shapes are refused."""
    cell, state, d = loaded
    fast = FastAdvance(cell.net)
    first = fast(*state, d)
    frozen = [np.array(a) for a in state]
    for a in frozen:
        a.flags.writeable = False
    strided = np.empty((d.shape[0], 4))
    strided[:, ::2] = d
    again = fast(*frozen, strided[:, ::2])
    for name in FastIncrement._fields:
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)
    single = fast(*(np.asarray(a, dtype=np.float32) for a in state), d)
    wanted = FastAdvance(cell.net)(*(np.asarray(a, dtype=np.float32).astype(np.float64) for a in state), d)
    np.testing.assert_array_equal(single.moment, wanted.moment)
    with pytest.raises(ValueError, match="state shapes"):
        fast(state[0], state[1][:, :-1], state[2], d)


def _autograd_tangent(net, state, d):
    """d(S_nn, S_tt)/d(eps_n, eps_t) (n, 2, 2) of ``MesoNet.advance`` by torch autograd."""
    d_eps = torch.from_numpy(np.asarray(d, dtype=np.float64)).clone().requires_grad_(True)
    step = net.advance(*(torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in state), d_eps)
    rows = [torch.autograd.grad(step.moment[:, i, i].sum(), d_eps, retain_graph=True)[0] for i in (0, 1)]
    return torch.stack(rows, dim=1).numpy()


def test_the_forward_mode_tangent_equals_the_autograd_tangent(loaded):
    """Same branches (capped and sliding contacts, zero and tiny probes); the float32 network rounds."""
    cell, state, d = loaded
    increment, tangent = FastAdvance(cell.net).increment(*state, d, with_tangent=True)
    expected = _autograd_tangent(cell.net, state, d)
    scale = np.abs(expected).max()
    assert scale > 1e8
    np.testing.assert_allclose(tangent, expected, rtol=0, atol=1e-5 * scale)
    assert np.abs(tangent[0]).max() > 0  # zero probe: the cell size still moves the contacts
    fast = FastAdvance(cell.net)(*state, d)
    for name in FastIncrement._fields:
        np.testing.assert_array_equal(getattr(increment, name), getattr(fast, name), err_msg=name)


def test_the_tangent_is_bit_identical_in_any_batch(loaded):
    cell, state, d = loaded
    fast = FastAdvance(cell.net)
    whole = fast.increment(*state, d, with_tangent=True)[1]
    index = np.array([5, 0, 39, 5])
    part = fast.increment(*(np.asarray(a)[index] for a in state), d[index], with_tangent=True)[1]
    np.testing.assert_array_equal(part, whole[index])


@pytest.mark.other_cpus("planar")
@pytest.mark.parametrize("setting", list(OTHER_CPUS))
def test_a_cells_increment_and_tangent_do_not_depend_on_the_cpus_vector_width(other_cpus, setting):
    """The compiled step of ``loaded`` re-run in a process compiled for narrower vectors (and other BLAS kernels,
    ``tests/other_cpus.py``): every field, the tangent included, bit-identical to this process, whole batch and
    sub-batch."""
    here, index, other = other_cpus.compare("planar", setting)
    assert "tangent" in here
    for name, value in here.items():
        np.testing.assert_array_equal(other[f"whole_{name}"], value, err_msg=f"{name}, {setting}")
        np.testing.assert_array_equal(other[f"part_{name}"], value[index], err_msg=f"{name} of a sub-batch, {setting}")


def test_the_states_exercise_the_contact_law_branches(loaded):
    cell, state, d = loaded
    ref = _reference(cell, state, d)
    assert ref.capped.any() and (~ref.capped.any(dim=1)).any()
    assert (np.asarray(state.shear_force) != 0).any()


# -- the DEM's rest rule: a free grain with no force that nothing reaches does not move ------------

def _random_net(ratio):
    """A randomly initialised network on a fines cell whose outputs move every free DOF by ~1e-4 D per 1e-4."""
    meso = resolve_mesostructure(f"hcell-fines:alpha0=50,ratio={ratio}")
    law = ContactLaw()
    schema = CellSchema.from_arrays(radius=meso.radius, reference_position=meso.position,
                                    reference_cell_size=meso.cell_size, driven=meso.driven, pairs=meso.pairs,
                                    outer=meso.outer, kn=law.kn, kt=law.kt, mu=law.mu,
                                    contact_tolerance=meso.contact_tolerance)
    torch.manual_seed(0)
    net = MesoNet(schema, torch.ones(schema.n_pairs, dtype=torch.bool), hidden=(16,))
    with torch.no_grad():
        net.mlp[-1].bias.normal_(std=3.0)  # "whatever the network outputs": rates of a few D per unit strain
        net.mlp[-1].weight.mul_(30.0)
    return meso, net


@pytest.fixture(scope="module")
def fines_net():
    """Fine grain of 0.6 r in the pore: ~0.1 r from every neighbour."""
    return _random_net(0.6)


def _fines_state(meso, net, n=6, squeeze=2e-3, seed=3):
    """Skeleton compressed affinely by ``squeeze`` (loaded contacts), fine grain(s) where the file puts them."""
    rng = np.random.default_rng(seed)
    free = net.schema.free_dofs.numpy()
    size = np.tile(meso.cell_size * (1.0 - squeeze), (n, 1))
    position = np.tile(meso.position[free[:, 0], free[:, 1]] * (1.0 - squeeze), (n, 1))
    shear = np.zeros((n, net.schema.n_pairs))
    d_eps = rng.normal(scale=1e-4, size=(n, 2))
    return size, position, shear, d_eps


def _fine_dofs(meso, net):
    """Free-DOF columns of the fine grain(s) (those with both axes free) and of the skeleton."""
    free = net.schema.free_dofs.numpy()
    fine_grains = np.flatnonzero(~meso.driven.any(axis=1))
    fine = np.isin(free[:, 0], fine_grains)
    return fine, ~fine


def test_a_force_free_grain_far_from_its_neighbours_stays_at_rest_in_both_paths(fines_net):
    meso, net = fines_net
    fine, skeleton = _fine_dofs(meso, net)
    assert fine.sum() == 2 and skeleton.any()
    state = _fines_state(meso, net)
    with torch.inference_mode():
        ref = net.advance(*(torch.from_numpy(a) for a in state))
        moved = net.displacement(*(torch.from_numpy(a) for a in state)).numpy()
    assert np.abs(moved[:, fine]).min() > 1e-6 * net.schema.diameter  # the network alone would move it
    assert np.abs(ref.moment.numpy()).max() > 0  # the skeleton is loaded
    fast = FastAdvance(net)(*state[:3], state[3])
    for path in (ref.free_position.numpy(), fast.free_position):
        np.testing.assert_array_equal(path[:, fine], state[1][:, fine])
        assert np.all(path[:, skeleton] != state[1][:, skeleton])
    np.testing.assert_array_equal(ref.held.numpy(), np.tile(fine, (6, 1)))
    np.testing.assert_array_equal(fast.grains_held, np.ones(6))
    np.testing.assert_allclose(fast.moment, ref.moment.numpy(), rtol=0, atol=1e-6 * np.abs(ref.moment.numpy()).max())


def _grain_next_to(meso, net, gap):
    """State with the fine grain at ``gap`` [m] from the driven grain 0 along the line of centres, force-free."""
    size, position, shear, d_eps = _fines_state(meso, net, n=2, squeeze=0.0)
    fine, _ = _fine_dofs(meso, net)
    g = net.schema.free_dofs.numpy()[fine][0, 0]
    towards = meso.position[0] - meso.position[g]
    distance = np.linalg.norm(towards)
    target = meso.position[0] - towards / distance * (meso.radius[0] + meso.radius[g] + gap)
    position[:, fine] = target
    return (size, position, shear), fine


def test_a_grain_reached_during_the_increment_is_released_in_both_paths():
    """Grain 0 is driven along n: compression brings it onto the fine grain (released), extension not (held)."""
    meso, net = _random_net(0.3)
    (size, position, shear), fine = _grain_next_to(meso, net, gap=1e-4)
    d_eps = np.array([[2e-4, 0.0], [-2e-4, 0.0]])  # grain 0 moves by ~2e-4 m towards / away from the centre
    state = (size, position, shear, d_eps)
    with torch.inference_mode():
        ref = net.advance(*(torch.from_numpy(a) for a in state))
        wanted = net.displacement(*(torch.from_numpy(a) for a in state)).numpy()
    fast = FastAdvance(net)(size, position, shear, d_eps)
    assert ref.held[0, fine].sum() == 0 and ref.held[1, fine].all()
    np.testing.assert_array_equal(fast.grains_held[:1], [0])
    assert fast.grains_held[1] >= 1
    np.testing.assert_allclose(ref.free_position.numpy()[0, fine], position[0, fine] + wanted[0, fine], rtol=1e-14)
    np.testing.assert_array_equal(ref.free_position.numpy()[1, fine], position[1, fine])
    # the float32 hidden layers round the displacement the network gives to ~1e-7
    np.testing.assert_allclose(fast.free_position, ref.free_position.numpy(), rtol=0, atol=1e-6 * np.abs(wanted).max())


def test_the_forward_mode_tangent_of_held_and_moving_grains_equals_autograd(fines_net):
    meso, net = fines_net
    state = _fines_state(meso, net)
    tangent = FastAdvance(net).increment(*state[:3], state[3], with_tangent=True)[1]
    expected = _autograd_tangent(net, state[:3], state[3])
    np.testing.assert_allclose(tangent, expected, rtol=0, atol=1e-5 * np.abs(expected).max())


def test_the_tangent_of_a_held_grain_matches_central_differences(fines_net):
    meso, net = fines_net
    fine, _ = _fine_dofs(meso, net)
    size, position, shear, d_eps = (torch.from_numpy(a) for a in _fines_state(meso, net))
    d = d_eps.clone().requires_grad_(True)
    step = net.advance(size, position, shear, d)
    assert step.held[:, fine].all()
    rows = [torch.autograd.grad(step.moment[:, i, i].sum(), d, retain_graph=True)[0] for i in (0, 1)]
    tangent = torch.stack(rows, dim=1).numpy()
    held_rows = torch.autograd.grad(step.free_position[:, fine].sum(), d, allow_unused=False)[0].numpy()
    assert np.all(held_rows == 0.0)
    h = 1e-8
    fd = np.zeros_like(tangent)
    with torch.inference_mode():
        for j in range(2):
            e = torch.zeros(2, dtype=torch.float64)
            e[j] = h
            plus, minus = net.advance(size, position, shear, d_eps + e), net.advance(size, position, shear, d_eps - e)
            fd[:, :, j] = (plus.moment - minus.moment).numpy()[:, [0, 1], [0, 1]] / (2 * h)
            np.testing.assert_array_equal(plus.free_position[:, fine].numpy(), minus.free_position[:, fine].numpy())
    scale = np.abs(fd).max()
    assert scale > 1e6
    np.testing.assert_allclose(tangent, fd, rtol=0, atol=1e-4 * scale)


def test_the_compiled_load_features_equal_the_torch_ones(loaded, tmp_path):
    """A network with ``load_features``: the compiled features and increment match the torch path,
    and the option survives a checkpoint."""
    cell, state, d = loaded
    torch.manual_seed(2)
    net = MesoNet(cell.net.schema, cell.net.active, hidden=(16,), load_features=True)
    n_base = cell.net.feature_mean.shape[0]
    rng = np.random.default_rng(4)
    net.set_normalisation(rng.normal(scale=0.1, size=n_base + int(net.active.sum())),
                          rng.uniform(0.5, 2.0, size=n_base + int(net.active.sum())), cell.net.rate_mean,
                          cell.net.rate_std)
    tensors = [torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in state]
    with torch.inference_mode():
        raw = net.raw_features(*tensors, torch.from_numpy(d))[0]
        expected = ((raw - net.feature_mean) / net.feature_std).numpy()
        ref = net.advance(*tensors, torch.from_numpy(d))
    fraction = raw[:, n_base:].numpy()
    assert np.all((fraction >= 0) & (fraction <= 1)) and np.any((fraction > 0.01) & (fraction < 0.5))
    fast = FastAdvance(net)
    step = fast(*state, d)
    np.testing.assert_allclose(fast.last_features().T, expected, rtol=1e-6, atol=1e-6)
    scale = np.abs(ref.moment.numpy()).max()
    np.testing.assert_allclose(step.moment, ref.moment.numpy(), rtol=0, atol=1e-5 * scale)
    from training.checkpoint import load_checkpoint, save_checkpoint
    meta = json.loads((ROOT / "homogenization/data/ann_default.json").read_text())
    keep = ("schema", "contact_law", "contact_tolerance", "mesostructure", "mesostructure_sha256")
    save_checkpoint(tmp_path / "m.pt", net, {k: meta[k] for k in keep})
    again, _ = load_checkpoint(tmp_path / "m.pt")
    assert again.load_features
    with torch.inference_mode():
        torch.testing.assert_close(again.raw_features(*tensors, torch.from_numpy(d))[0], raw, rtol=0, atol=0)
