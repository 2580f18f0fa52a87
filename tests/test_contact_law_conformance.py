"""Every copy of each contact law agrees: numpy, numba, torch, Warp (planar and spatial), the closed form.

The same random contacts (overlaps, zero and negative ones, tangential increments that stick
and that slide in both directions) drive each language's law; the reference is the law of
docs/model.md written out below branch by branch, in plain Python floats. The linear law runs in
every runtime; the Hertz-Mindlin law in numpy, the spatial Warp kernel's law and the closed form
(the meso-ANN's numba and torch copies refuse it), and its DEM and closed form are compared on one
ten-sphere cell, forces and consistent tangents.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch
import warp as wp

from homogenization.backends.analytical import AnalyticalCell
from training import cell_physics, fast_cells
from warp_hcell.core import contact
from warp_hcell.core.laws import hertz_mindlin as hertz_numpy
from warp_hcell.core.parameters import ContactLaw, HertzMindlinLaw
from warp_hcell.dem import contact as warp_contact
from warp_hcell.dem.laws import hertz_mindlin as hertz_warp
from warp_hcell.mesostructures.hcell import h_cell

LAW = ContactLaw()
KN, KT, MU = LAW.kn, LAW.kt, LAW.mu
N = 4000


@pytest.fixture(scope="module")
def contacts():
    """(overlap [m], old tangential force [N], tangential increment [m]), each (N,): a quarter
    without overlap (gaps and exact zeros), the rest loaded, increments from well inside the
    cap to several times past it on either side."""
    rng = np.random.default_rng(23)
    overlap = rng.uniform(1e-7, 1e-4, N)
    overlap[: N // 8] = -rng.uniform(0.0, 1e-4, N // 8)
    overlap[N // 8: N // 4] = 0.0
    cap = MU * KN * np.maximum(overlap, 0.0)
    old = rng.uniform(-1.0, 1.0, N) * cap
    increment = rng.uniform(-3.0, 3.0, N) * (cap + KN * 1e-6) / KT
    return overlap, old, increment


def reference(overlap, old, increment):
    """The law case by case: (f_n, f_s, regime: 1 stick, 2 slide)."""
    fn, fs, regime = np.empty(N), np.empty(N), np.empty(N, dtype=np.int64)
    for k, (o, f, du) in enumerate(zip(overlap.tolist(), old.tolist(), increment.tolist())):
        fn[k] = KN * o if o > 0.0 else 0.0
        trial = f + KT * du
        cap = MU * fn[k]
        fs[k] = math.copysign(cap, trial) if abs(trial) > cap else trial
        regime[k] = 2 if fn[k] > 0.0 and abs(fs[k]) >= cap else 1
    return fn, fs, regime


def test_the_random_contacts_stick_and_slide_both_ways(contacts):
    fn, fs, regime = reference(*contacts)
    assert np.count_nonzero(fn == 0.0) == N // 4
    loaded = fn > 0.0
    for sign in (1.0, -1.0):
        assert np.count_nonzero(loaded & (regime == 2) & (np.sign(fs) == sign)) > N // 10
    assert np.count_nonzero(loaded & (regime == 1)) > N // 10


def test_numpy(contacts):
    overlap, old, increment = contacts
    fn, fs, regime = reference(*contacts)
    normal = contact.normal_force(overlap, KN)
    shear = contact.tangential_force(old, increment, normal, KT, MU)
    np.testing.assert_array_equal(normal, fn)
    np.testing.assert_array_equal(shear, fs)
    np.testing.assert_array_equal(contact.regime(normal, shear, MU), regime)


@numba.njit
def _numba_law(overlap, old, increment, kn, kt, mu, normal, shear):
    for k in range(overlap.shape[0]):
        normal[k] = fast_cells.normal_force(overlap[k], kn)
        shear[k] = fast_cells.coulomb_cap(old[k] + kt * increment[k], normal[k], mu)


def test_numba_copies_that_the_meso_ann_inference_calls(contacts):
    fn, fs, _ = reference(*contacts)
    normal, shear = np.empty(N), np.empty(N)
    _numba_law(*contacts, KN, KT, MU, normal, shear)
    np.testing.assert_array_equal(normal, fn)
    np.testing.assert_array_equal(shear, fs)


def test_torch(contacts):
    overlap, old, increment = (torch.from_numpy(a) for a in contacts)
    fn, fs, _ = reference(*contacts)
    normal = cell_physics.normal_force(overlap, KN)
    shear = cell_physics.coulomb_cap(old + KT * increment, normal, MU)
    np.testing.assert_array_equal(normal.numpy(), fn)
    np.testing.assert_array_equal(shear.numpy(), fs)


@wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
def _warp_law(overlap: wp.array(dtype=wp.float64), old: wp.array(dtype=wp.float64),
              increment: wp.array(dtype=wp.float64), kn: wp.float64, kt: wp.float64, mu: wp.float64,
              normal: wp.array(dtype=wp.float64), shear: wp.array(dtype=wp.float64),
              regime: wp.array(dtype=wp.float64), normal_3d: wp.array(dtype=wp.float64),
              shear_3d: wp.array(dtype=wp.vec3d), regime_3d: wp.array(dtype=wp.float64)):
    k = wp.tid()
    f_n, f_s = warp_contact.contact_law(overlap[k], increment[k], old[k], kn, kt, mu)
    normal[k] = f_n
    shear[k] = f_s
    regime[k] = warp_contact.contact_regime(f_n, wp.abs(f_s), mu * f_n)
    # the same contact in space: the tangential spring along t2, its plane normal along n
    zero = wp.float64(0.0)
    carried = warp_contact.carried_spring(wp.vec3d(zero, zero, old[k]), wp.vec3d(wp.float64(1.0), zero, zero))
    f_n3, f_s3, regime3 = warp_contact.contact_law_3d(overlap[k], wp.vec3d(zero, zero, increment[k]), carried,
                                                      kn, kt, mu)
    normal_3d[k] = f_n3
    shear_3d[k] = f_s3
    regime_3d[k] = regime3


def test_warp_planar_and_spatial_laws_of_the_dem_kernels(contacts):
    fn, fs, regime = reference(*contacts)
    inputs = [wp.array(a, dtype=wp.float64, device="cpu") for a in contacts]
    outputs = [wp.zeros(N, dtype=wp.float64, device="cpu") for _ in range(4)]
    shear_3d = wp.zeros(N, dtype=wp.vec3d, device="cpu")
    regime_3d = wp.zeros(N, dtype=wp.float64, device="cpu")
    wp.launch(_warp_law, dim=N, inputs=[*inputs, KN, KT, MU, *outputs, shear_3d, regime_3d], device="cpu")
    normal, shear, warp_regime, normal_3d = (a.numpy() for a in outputs)
    np.testing.assert_array_equal(normal, fn)
    np.testing.assert_array_equal(shear, fs)
    np.testing.assert_array_equal(warp_regime, regime)
    # in space the cap scales the trial vector: cap * (trial / size), round-off of the division
    np.testing.assert_array_equal(normal_3d, fn)
    s3 = shear_3d.numpy()
    np.testing.assert_array_equal(s3[:, :2], 0.0)
    np.testing.assert_allclose(s3[:, 2], fs, rtol=5e-16, atol=0.0)
    np.testing.assert_array_equal(regime_3d.numpy(), regime)


def test_warp_spatial_cap_acts_along_the_trial_force():
    rng = np.random.default_rng(5)
    overlap = rng.uniform(1e-6, 1e-4, N)
    trial = rng.normal(size=(N, 3)) * MU * KN * overlap[:, None]
    trial[:, 0] = 0.0  # in the tangent plane of n = e1
    inputs = [wp.array(overlap, dtype=wp.float64, device="cpu"), wp.array(trial, dtype=wp.vec3d, device="cpu")]
    shear = wp.zeros(N, dtype=wp.vec3d, device="cpu")
    regime = wp.zeros(N, dtype=wp.float64, device="cpu")
    wp.launch(_spatial_law, dim=N, inputs=[*inputs, KN, KT, MU, shear, regime], device="cpu")
    size = np.linalg.norm(trial, axis=1)
    cap = MU * KN * overlap
    expected = trial * np.minimum(1.0, cap / size)[:, None]
    np.testing.assert_allclose(shear.numpy(), expected, rtol=1e-15, atol=1e-15 * cap.max())
    np.testing.assert_array_equal(regime.numpy(), np.where(size >= cap, 2.0, 1.0))
    assert 0.1 * N < np.count_nonzero(size >= cap) < 0.9 * N


@wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
def _spatial_law(overlap: wp.array(dtype=wp.float64), trial: wp.array(dtype=wp.vec3d), kn: wp.float64,
                 kt: wp.float64, mu: wp.float64, shear: wp.array(dtype=wp.vec3d), regime: wp.array(dtype=wp.float64)):
    k = wp.tid()
    zero = wp.float64(0.0)
    _, f_s, r = warp_contact.contact_law_3d(overlap[k], wp.vec3d(zero, zero, zero), trial[k], kn, kt, mu)
    shear[k] = f_s
    regime[k] = r


def test_the_analytical_closed_form_obeys_the_law():
    """After each increment the H-cell's N1, N2 and T1 are the law at the cell's own geometry: normal
    forces from the type-1 branch and from y2, T1 from the spring grown along the mid-increment arc."""
    model = AnalyticalCell(LAW, 0.5)
    alpha0 = np.repeat([35.0, 45.0, 60.0, 75.0], 4)
    c2 = np.tile(np.cos(2 * np.linspace(0.0, np.pi / 2, 4)), 4)
    state = model.init_state([h_cell(a, 0.5) for a in alpha0], alpha0.size)
    d = model.diameter
    steps = [np.full((alpha0.size, 2), 5e-6)] * 100 + [np.stack([1e-5 * c2, -1e-5 * c2], axis=1)] * 300
    slid = stuck = 0
    for d_eps in steps:
        new, _ = model.step(state, d_eps)
        np.testing.assert_array_equal(new.N1, contact.normal_force(d - new.d1, KN))
        np.testing.assert_array_equal(new.N2, contact.normal_force(d - 2.0 * new.y2, KN))
        increment = 0.5 * (state.d1 + new.d1) * (new.alpha - state.alpha)
        # the backend multiplies kt d1_mid d_alpha in another order: round-off of the trial's terms
        law = contact.tangential_force(state.T1, increment, new.N1, KT, MU)
        assert np.all(np.abs(new.T1 - law) <= 1e-15 * (np.abs(state.T1) + np.abs(KT * increment)))
        regime = contact.regime(new.N1, new.T1, MU)
        slid += np.count_nonzero((new.N1 > 0.0) & (regime == contact.SLIDE))
        stuck += np.count_nonzero((new.N1 > 0.0) & (regime == contact.STICK))
        state = new
    assert slid > 100 and stuck > 100


# -- the Hertz-Mindlin law: numpy, Warp (spatial DEM kernel), the closed form ---------------------------
# (the numba and torch copies serve the meso-ANN, which refuses any law but the linear one)

HERTZ = HertzMindlinLaw()


@pytest.fixture(scope="module")
def hertz_contacts():
    """(overlap, start overlap, old tangential force, tangential increment, kh, ks), each (N,): pairs
    of random radii, a quarter without overlap, the rest loaded, the overlap before the move within
    10 % of the overlap (a tenth of them from no overlap: closing), increments sticking and sliding
    both ways."""
    rng = np.random.default_rng(29)
    r_i, r_j = rng.uniform(0.3, 0.7, N), rng.uniform(0.3, 0.7, N)
    kh, ks = hertz_numpy.pair_constants(HERTZ, r_i, r_j)
    overlap = rng.uniform(1e-7, 1e-3, N)
    overlap[: N // 8] = -rng.uniform(0.0, 1e-4, N // 8)
    overlap[N // 8: N // 4] = 0.0
    spring_overlap = overlap * rng.uniform(0.9, 1.1, N)
    spring_overlap[N // 4: N // 4 + N // 10] = -rng.uniform(0.0, 1e-5, N // 10)
    normal = kh * np.maximum(overlap, 0.0) ** 1.5
    cap = HERTZ.mu * normal
    old = rng.uniform(-1.0, 1.0, N) * cap
    stiffness = ks * np.sqrt(np.maximum(spring_overlap, 1e-9))
    increment = rng.uniform(-3.0, 3.0, N) * (cap + 1e3) / stiffness
    return overlap, spring_overlap, old, increment, kh, ks


def hertz_reference(overlap, spring_overlap, old, increment, kh, ks):
    """The Hertz-Mindlin law case by case in Python floats: (f_n, f_s, regime); the spring grows by
    the mean of ks sqrt(delta) over the move, delta linear from the start overlap to the overlap."""
    fn, fs, regime = np.empty(N), np.empty(N), np.empty(N, dtype=np.int64)
    mu = HERTZ.mu
    for k in range(N):
        delta = max(float(overlap[k]), 0.0)
        fn[k] = float(kh[k]) * (delta * math.sqrt(delta))
        a, b = math.sqrt(delta), math.sqrt(max(float(spring_overlap[k]), 0.0))
        stiffness = (2.0 / 3.0) * float(ks[k]) * ((a * a + a * b + b * b) / (a + b)) if a + b > 0.0 else 0.0
        trial = float(old[k]) + stiffness * float(increment[k])
        cap = mu * fn[k]
        fs[k] = math.copysign(cap, trial) if abs(trial) > cap else trial
        regime[k] = 2 if fn[k] > 0.0 and abs(fs[k]) >= cap else 1
    return fn, fs, regime


def test_the_hertz_contacts_stick_and_slide_both_ways(hertz_contacts):
    fn, fs, regime = hertz_reference(*hertz_contacts)
    assert np.count_nonzero(fn == 0.0) == N // 4
    for sign in (1.0, -1.0):
        assert np.count_nonzero((fn > 0.0) & (regime == 2) & (np.sign(fs) == sign)) > N // 10
    assert np.count_nonzero((fn > 0.0) & (regime == 1)) > N // 10
    # the normal force is (4/3) E* sqrt(R*) delta^(3/2) of the grain material (YADE's kno uN^1.5)
    overlap, _, _, _, kh, _ = hertz_contacts
    loaded = overlap > 0.0
    np.testing.assert_allclose(fn[loaded] / overlap[loaded] ** 1.5, kh[loaded], rtol=1e-13)


def test_numpy_hertz(hertz_contacts):
    overlap, spring_overlap, old, increment, kh, ks = hertz_contacts
    fn, fs, regime = hertz_reference(*hertz_contacts)
    law = contact.PairLaw(HERTZ.name, kh, ks)
    normal = law.normal(overlap)
    shear = contact.tangential_force(old, increment, normal, law.move_stiffness(spring_overlap, overlap), HERTZ.mu)
    np.testing.assert_array_equal(normal, fn)
    np.testing.assert_array_equal(shear, fs)
    np.testing.assert_array_equal(contact.regime(normal, shear, HERTZ.mu), regime)


@wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
def _warp_hertz(overlap: wp.array(dtype=wp.float64), spring_overlap: wp.array(dtype=wp.float64),
                old: wp.array(dtype=wp.float64), increment: wp.array(dtype=wp.float64),
                kh: wp.array(dtype=wp.float64), ks: wp.array(dtype=wp.float64), mu: wp.float64,
                normal: wp.array(dtype=wp.float64), shear: wp.array(dtype=wp.vec3d), regime: wp.array(dtype=wp.float64)):
    k = wp.tid()
    zero = wp.float64(0.0)
    carried = warp_contact.carried_spring(wp.vec3d(zero, zero, old[k]), wp.vec3d(wp.float64(1.0), zero, zero))
    f_n, f_s, r = hertz_warp.contact_law_3d(overlap[k], spring_overlap[k], wp.vec3d(zero, zero, increment[k]),
                                                    carried, kh[k], ks[k], mu)
    normal[k] = f_n
    shear[k] = f_s
    regime[k] = r


def test_warp_hertz_law_of_the_spatial_dem_kernel(hertz_contacts):
    fn, fs, regime = hertz_reference(*hertz_contacts)
    inputs = [wp.array(a, dtype=wp.float64, device="cpu") for a in hertz_contacts]
    normal = wp.zeros(N, dtype=wp.float64, device="cpu")
    shear = wp.zeros(N, dtype=wp.vec3d, device="cpu")
    warp_regime = wp.zeros(N, dtype=wp.float64, device="cpu")
    wp.launch(_warp_hertz, dim=N, inputs=[*inputs, HERTZ.mu, normal, shear, warp_regime], device="cpu")
    np.testing.assert_array_equal(normal.numpy(), fn)
    s3 = shear.numpy()
    np.testing.assert_array_equal(s3[:, :2], 0.0)
    # the spatial cap scales the trial vector: cap * (trial / size), round-off of the division
    np.testing.assert_allclose(s3[:, 2], fs, rtol=5e-16, atol=0.0)
    np.testing.assert_array_equal(warp_regime.numpy(), regime)


def test_the_hertz_dem_kernel_and_the_closed_form_give_the_same_cell():
    """Both runtimes of the law on one ten-sphere cell (isotropic, then isochoric shear that slides):
    the same Love-Weber moment to 1e-3 of its largest value (measured 4.7e-4; the linear law on this
    path: 6.6e-5). The incremental Mindlin spring integrates kt(delta) du along the path the DEM's
    free grains take while they relax, which the quasi-static closed form does not see."""
    from warp_hcell.mesostructures.builders import resolve_mesostructure
    from homogenization.backends import make_cell_model

    meso = resolve_mesostructure("hcell3d:alpha0=55")
    lateral = 1.0 - 1.0 / math.sqrt(1.0 - 4e-5)
    path = [np.array([[2e-5, 2e-5, 2e-5]])] * 10 + [np.array([[4e-5, lateral, lateral]])] * 60
    moments = {}
    for backend in ("dem", "analytical"):
        model = make_cell_model(backend, dim=3, contact_law=HERTZ)
        state = model.init_state(meso, 1)
        rows = []
        for d_eps in path:
            state, response = model.step(state, d_eps)
            rows.append(np.diag(response.moment[0]))
        moments[backend] = np.array(rows)
    scale = np.abs(moments["analytical"]).max()
    assert np.abs(moments["dem"] - moments["analytical"]).max() <= 1e-3 * scale


def test_the_analytical_closed_form_obeys_the_hertz_law():
    """The planar solve of the ten-sphere cell's planes: after each increment N1, N2 are the Hertz law
    at the cell's own geometry and T1 the spring grown with the mean kt of the increment's overlaps."""
    model = AnalyticalCell(HERTZ, 0.5)
    law = model.law
    alpha0 = np.repeat([50.0, 60.0, 75.0], 4)
    c2 = np.tile(np.cos(2 * np.linspace(0.0, np.pi / 2, 4)), 3)
    state = model.touching_state(alpha0, alpha0.size)
    d = model.diameter
    steps = [np.full((alpha0.size, 2), 2e-5)] * 20 + [np.stack([4e-5 * c2, -4e-5 * c2], axis=1)] * 100
    slid = stuck = 0
    for d_eps in steps:
        new, _ = model.step(state, d_eps)
        np.testing.assert_array_equal(new.N1, hertz_numpy.normal_force(d - new.d1, law.kn))
        np.testing.assert_array_equal(new.N2, hertz_numpy.normal_force(d - 2.0 * new.y2, law.kn))
        d1_mid = 0.5 * (state.d1 + new.d1)
        increment = d1_mid * (new.alpha - state.alpha)
        kt = law.move_stiffness(d - state.d1, d - new.d1)
        expected = contact.tangential_force(state.T1, increment, new.N1, kt, HERTZ.mu)
        assert np.all(np.abs(new.T1 - expected) <= 1e-15 * (np.abs(state.T1) + np.abs(kt * increment)))
        regime = contact.regime(new.N1, new.T1, HERTZ.mu)
        slid += np.count_nonzero((new.N1 > 0.0) & (regime == contact.SLIDE))
        stuck += np.count_nonzero((new.N1 > 0.0) & (regime == contact.STICK))
        state = new
    assert slid > 50 and stuck > 50


def test_the_hertz_dem_tangent_is_the_closed_forms():
    """The DEM's condensed tangent (``warp_hcell.dem.tangent``, numpy Hertz-Mindlin stiffnesses) and the
    closed form's consistent tangent of the same ten-sphere cell after axial loading: within 8e-11 of
    the largest entry (measured 1.6e-11)."""
    from warp_hcell.mesostructures.builders import resolve_mesostructure
    from homogenization.backends import make_cell_model

    meso = resolve_mesostructure("hcell3d:alpha0=55")
    tangents = {}
    for backend in ("dem", "analytical"):
        model = make_cell_model(backend, dim=3, contact_law=HERTZ)
        state = model.init_state(meso, 1)
        for k in range(20):
            state, response = model.step(state, np.array([[1e-4, 0.0, 0.0]]), with_tangent=k == 19)
        tangents[backend] = response.tangent[0]
    scale = np.abs(tangents["analytical"]).max()
    assert np.abs(tangents["dem"] - tangents["analytical"]).max() <= 8e-11 * scale
