"""Equilibrium corrections of the 3D meso-ANN step (``training.fast_equilibrium3d``, ``training.equilibrium``,
``AnnCell(equilibrium_corrections=K)``, ``hmodel triaxial --equilibrium-corrections``).

Oracles nobody here derived the same way: the residual and Jacobian of the compiled kernel against
torch autograd of ``training.cell_physics`` (the DEM's contact law in torch), one pair's Jacobian
against central finite differences of its force, and the tangent of the corrected step against
central finite differences of the step. Measured: residual within 8e-15 of the largest normal force
and Jacobian within 1.9e-16 of its largest entry; pair Jacobians within 9e-9 of the largest entry (steps
of 1e-8 m); corrected compiled and torch steps within 3.6e-15 of the largest moment; tangent within
4.9e-9 of the largest entry (steps of 1e-7). The tolerances are about 5 times these.
"""

import subprocess
import sys
from pathlib import Path

import json

import h5py
import numpy as np
import pytest
import torch

from other_cpus import HARD_CASES, OTHER_CPUS, relaxing_network, sheared as shared_sheared, sheared_probe, sub_batch
from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell, AnnCell3D
from training import cell_physics
from training.equilibrium import balance, corrected_advance
from training.fast_cells import grain_positions
from training.fast_equilibrium3d import pair_force_jacobian, residual3, residual_jacobian3
from training.inference import _cells_last, FastAdvance
from warp_hcell.core.contact import CAP_SLACK
from warp_hcell.core.parameters import ContactLaw

ROOT = Path(__file__).resolve().parents[1]
needs_model = pytest.mark.skipif(not default_model_path(3).is_file(), reason="no shipped 3D model")


@pytest.fixture(scope="module")
def sheared():
    """30 spatial cells of the shipped model, compressed isotropically then sheared at random deviatoric
    rates (contacts slide), and one undrained probe."""
    return shared_sheared()


@needs_model
def test_the_compiled_residual_and_jacobian_are_torch_autograd_of_the_contact_law(sheared):
    cell, _, state, d_eps = sheared
    fast = cell.fast
    size, free, shear = (np.asarray(a) for a in state)
    d_free = fast(size, free, shear, d_eps).free_position - free
    work = fast._workspace(size.shape[0])
    fast._features(_cells_last(size), _cells_last(free), _cells_last(shear), d_eps, fast.cells, fast.law, fast.scaling,
                   work.before)
    n, n_free = free.shape
    x = np.empty((fast.cells.frac.shape[0], 3, n))
    grain_positions(np.ascontiguousarray((size * (1 - d_eps)).T), np.ascontiguousarray((free + d_free).T),
                    fast.cells.frac, fast.cells.free_dofs, x)
    residual, jacobian, fn_max = np.empty((n_free, n)), np.empty((n, n_free, n_free)), np.empty(n)
    residual_jacobian3(x, _cells_last(shear), work.before.old_branch, work.before.old_contact, fast.cells, fast.law,
                       np.ones(n, dtype=bool), residual, jacobian, fn_max)
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    trial = t(d_free).requires_grad_(True)
    schema = cell.net.schema
    old = cell_physics.contacts(schema, cell_physics.positions(schema, t(size), t(free)))
    ref, ref_fn = balance(schema, t(size), t(free), t(shear), t(d_eps), trial, old)
    ref_jac = torch.stack([torch.autograd.grad(ref[:, k].sum(), trial, retain_graph=True)[0] for k in range(n_free)], 1)
    assert np.abs(residual).max() > 0 and np.abs(jacobian).max() > 0
    assert np.abs(residual.T - ref.detach().numpy()).max() <= 5e-14 * fn_max.max()  # the unbalance cancels pair forces
    assert np.abs(jacobian - ref_jac.numpy()).max() <= 1e-15 * np.abs(jacobian).max()
    assert np.array_equal(fn_max, ref_fn.detach().numpy())
    alone, alone_fn = np.empty((n_free, n)), np.empty(n)
    residual3(x, _cells_last(shear), work.before.old_branch, work.before.old_contact, fast.cells, fast.law, alone, alone_fn)
    assert np.array_equal(alone, residual) and np.array_equal(alone_fn, fn_max)  # the residual pass without Jacobian


@pytest.mark.parametrize("case", ["sticking", "carried", "capped", "no_history"])
def test_one_pairs_jacobian_is_the_finite_difference_of_its_force(case):
    kn, kt, mu = 2e8, 1e8, 0.5
    rsum = 1.0
    rng = np.random.default_rng(["sticking", "carried", "capped", "no_history"].index(case))
    ob = np.array([0.3, -0.5, 0.79])
    ob *= (rsum - 2e-3) / np.linalg.norm(ob)
    b = ob + 1e-4 * rng.standard_normal(3)
    u_old = ob / np.linalg.norm(ob)
    s = np.cross(u_old, rng.standard_normal(3))
    s *= {"sticking": 1e3, "carried": 5e4, "capped": 3e5, "no_history": 0.0}[case] / np.linalg.norm(s)
    g, dg, work = np.empty(3), np.empty((3, 3)), np.empty((8, 3, 3))

    def force(branch):
        out = np.empty(3)
        pair_force_jacobian(branch, ob, s, case != "no_history", rsum, rsum * (1 + 1e-9), kn, kt, mu, 1 + CAP_SLACK,
                            out, np.empty((3, 3)), work)
        return out

    assert pair_force_jacobian(b, ob, s, case != "no_history", rsum, rsum * (1 + 1e-9), kn, kt, mu, 1 + CAP_SLACK,
                               g, dg, work)
    h = 1e-8
    fd = np.column_stack([(force(b + h * e) - force(b - h * e)) / (2 * h) for e in np.eye(3)])
    assert np.abs(dg - fd).max() <= 5e-8 * np.abs(fd).max()


@needs_model
def test_corrections_bring_every_cell_to_the_dem_tolerance_and_are_counted(sheared):
    cell, _, state, d_eps = sheared

    def corrected(fast, d):
        return fast(*state, d), fast.last_corrections()

    assert corrected(cell.fast, d_eps)[1] is None
    _, (ratio, steps, *_) = corrected(FastAdvance(cell.net, 3, 1e-6), d_eps)
    assert (ratio[0] > 1e-6).all()  # the network alone leaves every cell off balance here
    assert (ratio[1] <= 1e-6).all()
    assert ((steps >= 1) & (steps <= 3)).all()
    _, (still_ratio, *_) = corrected(FastAdvance(cell.net, 3, 1e-6, guess="still"), d_eps)
    assert (still_ratio[0] > ratio[0]).all()
    assert (still_ratio[1] <= 1e-6).all()
    none, (_, none_steps, *_) = corrected(FastAdvance(cell.net, 3, 1e-6), np.zeros_like(d_eps))
    assert np.array_equal(none_steps, np.zeros(d_eps.shape[0], dtype=np.int64))  # a zero increment stays a no-op
    assert np.array_equal(none.free_position, np.asarray(state.free_position))


def assert_same_on_other_cpus(other_cpus, check: str) -> None:
    """Every field of ``check``'s corrected increment (``tests/other_cpus.py``), counts included, bit-identical on each
    other CPU to this process, whole batch and sub-batch."""
    for setting in OTHER_CPUS:
        here, index, other = other_cpus.compare(check, setting)
        for name, value in here.items():
            np.testing.assert_array_equal(other[f"whole_{name}"], value, err_msg=f"{name}, {setting}")
            np.testing.assert_array_equal(other[f"part_{name}"], sub_batch(name, value, index),
                                          err_msg=f"{name} of a sub-batch, {setting}")


@needs_model
@pytest.mark.other_cpus("corrected")
def test_a_cells_corrected_increment_is_bit_identical_in_any_batch_and_on_other_cpus(sheared, other_cpus):
    cell, _, state, d_eps = sheared
    d_eps = sheared_probe(d_eps)
    fast = FastAdvance(cell.net, 2, 1e-6)
    whole = {**fast(*state, d_eps)._asdict(), **fast.last_corrections()._asdict()}
    index = np.array([5, 0, 29, 5, 17])
    part = {**fast(*(np.asarray(a)[index] for a in state), d_eps[index])._asdict(), **fast.last_corrections()._asdict()}
    for name, value in part.items():
        np.testing.assert_array_equal(np.asarray(value), sub_batch(name, np.asarray(whole[name]), index), err_msg=name)
    assert_same_on_other_cpus(other_cpus, "corrected")


@needs_model
def test_torch_and_compiled_corrections_agree_and_the_tangent_is_the_equilibriums(sheared):
    _, meso, state, d_eps = sheared
    cell = AnnCell3D(ContactLaw(), 0.5, equilibrium_corrections=3)
    compiled_state, compiled = cell.step(state, d_eps)
    fast, cell.fast = cell.fast, None
    torch_state, torch_response = cell.step(state, d_eps, with_tangent=True)
    cell.fast = fast
    scale = np.abs(compiled.moment).max()
    assert np.abs(compiled.moment - torch_response.moment).max() <= 2e-14 * scale
    for key in ("n_corrected", "n_corrections", "n_shortened", "n_shifted", "n_unconverged"):
        assert compiled.diagnostics[key] == torch_response.diagnostics[key]
    h = 1e-7
    fd = np.empty_like(torch_response.tangent)
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        _, plus = cell.step(state, d_eps + step)
        _, minus = cell.step(state, d_eps - step)
        fd[:, :, j] = (np.diagonal(plus.moment, axis1=1, axis2=2) - np.diagonal(minus.moment, axis1=1, axis2=2)) / (2 * h)
    assert np.abs(fd - torch_response.tangent).max() <= 2.5e-8 * np.abs(fd).max()


def test_globalised_corrections_balance_cells_where_full_newton_steps_do_not():
    net = relaxing_network()
    data = np.load(HARD_CASES)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    d_eps = data["d_eps"]
    full = FastAdvance(net, 20, 1e-4, halvings=0, shift=0.0)
    full(*state, d_eps)
    assert (full.last_corrections().force_ratio[1] > 1e-2).all()  # full steps leave every case off balance
    fast = FastAdvance(net, 20, 1e-4)
    inc = fast(*state, d_eps)
    ratio, steps, shortened, shifted = fast.last_corrections()
    assert ((ratio[1] > 0) & (ratio[1] <= 1e-4)).all() and (steps <= 20).all()
    assert (shifted[:3] >= 1).all() and (shifted[3:] == 0).all() and (shortened[3:] >= 1).all()
    assert ((shortened + shifted) <= steps).all()
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    schema = net.schema
    old = cell_physics.contacts(schema, cell_physics.positions(schema, t(state[0]), t(state[1])))
    residual, fn_max = balance(schema, *(t(a) for a in state), t(d_eps), t(inc.free_position - state[1]), old)
    assert (residual.abs().amax(dim=1) <= 1.001e-4 * fn_max).all()  # balanced by the torch contact law too
    with torch.no_grad():
        out = corrected_advance(net, *(t(a) for a in state), t(d_eps), 20, 1e-4)
    for name, compiled, other in (("steps", steps, out.corrections), ("shortened", shortened, out.shortened),
                                  ("shifted", shifted, out.shifted)):
        np.testing.assert_array_equal(compiled, other.numpy(), err_msg=name)
    assert np.abs(out.increment.free_position.numpy() - inc.free_position).max() <= 1e-14


@pytest.mark.other_cpus("globalised")
def test_globalised_corrections_are_bit_identical_in_any_batch_and_on_other_cpus(other_cpus):
    fast = FastAdvance(relaxing_network(), 20)  # the DEM's tolerance, as in tests/other_cpus.py
    data = np.load(HARD_CASES)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    whole = {**fast(*state, data["d_eps"])._asdict(), **fast.last_corrections()._asdict()}
    assert whole["shortened"].sum() > 0 and whole["shifted"].sum() > 0  # both rules fire here
    index = np.array([4, 0, 2, 0])
    part = {**fast(*(a[index] for a in state), data["d_eps"][index])._asdict(), **fast.last_corrections()._asdict()}
    for name, value in part.items():
        np.testing.assert_array_equal(np.asarray(value), sub_batch(name, np.asarray(whole[name]), index), err_msg=name)
    assert_same_on_other_cpus(other_cpus, "globalised")


@needs_model
def test_the_hybrid_is_declared_and_the_planar_model_refuses_it():
    cell = AnnCell3D(ContactLaw(), 0.5, equilibrium_corrections=2)
    assert cell.certificate_problem is not None and "equilibrium corrections" in cell.certificate_problem
    assert AnnCell3D(ContactLaw(), 0.5).certificate_problem is None
    with pytest.raises(ValueError, match="spatial model only"):
        AnnCell(ContactLaw(), 0.5, equilibrium_corrections=1)
    with pytest.raises(ValueError, match="equilibrium corrections"):
        AnnCell3D(ContactLaw(), 0.5, equilibrium_corrections=-1)


def _hmodel(*argv, cwd):
    return subprocess.run([sys.executable, "-m", "homogenization.hmodel", "triaxial", *argv], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


@needs_model
def test_triaxial_records_the_corrections_and_refuses_them_without_the_ann(tmp_path):
    common = ["--p0", "2e5", "--undrained", "--eps-max", "0.01", "--increment", "1e-3", "--order", "3", "--spins", "1"]
    refused = _hmodel("--backend", "dem", *common, "--equilibrium-corrections", "2", "--out", str(tmp_path / "d"),
                      cwd=ROOT)
    assert refused.returncode == 2 and "--equilibrium-corrections applies to --backend ann" in refused.stderr
    uncertified = _hmodel("--backend", "ann", *common, "--equilibrium-corrections", "2", "--out", str(tmp_path / "u"),
                          cwd=ROOT)
    assert uncertified.returncode == 2 and "equilibrium corrections" in uncertified.stderr
    done = _hmodel("--backend", "ann", *common, "--equilibrium-corrections", "2", "--uncertified-ok",
                   "--out", str(tmp_path / "a"), cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "equilibrium corrections:" in done.stdout
    with h5py.File(tmp_path / "a" / "run.h5") as f:
        parameters = json.loads(f.attrs["parameters"])
        corrected = f["diagnostics/n_corrected"][()]
    assert corrected.sum() > 0
    assert parameters["backend_options"]["equilibrium_corrections"] == 2
    assert parameters["ann_model"]["equilibrium_corrections"] == 2 and parameters["ann_model"]["certified"] is False
