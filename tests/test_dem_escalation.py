"""The hybrid's released grains (``homogenization.ann.escalation``): the cells where a free grain moved and
ends pressed by nothing are found grain by grain, taken again with that grain starting the corrections at rest,
and counted; the DEM's increment from rest that other devices take is the DEM's equilibrium."""

from pathlib import Path

import numpy as np
import pytest

from other_cpus import relaxing_network
from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell3D
from homogenization.ann.escalation import DemEscalation, RELEASE_RULE, RELEASE_RULE_AFTER
from training.inference import FastAdvance
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.database.learning_state import evaluate
from warp_hcell.mesostructures.builders import mesostructure_arg

ROOT = Path(__file__).resolve().parents[1]
LARGE_AXIAL = ROOT / "benchmarks" / "cells" / "large_axial.toml"
HARD_CASES = ROOT / "tests" / "data" / "equilibrium" / "large_axial_hard.npz"
SHIPPED_3D = default_model_path(3)


def _pair_forces_by_hand(schema, size, free, kn) -> dict[tuple[int, int], float]:
    """{(i, j): normal force} of one cell's pairs (linear law, f_n = kn overlap): the reference positions scaled to
    ``size`` (dim,), the free DOFs at ``free`` (n_free,)."""
    x = schema.reference_position * size / schema.reference_cell_size
    for k, (grain, axis) in enumerate(schema.free_dofs):
        x[grain, axis] = free[k]
    return {(int(i), int(j)): kn * max(schema.radius[i] + schema.radius[j] - np.linalg.norm(x[j] - x[i]), 0.0)
            for i, j in schema.pairs}


def _released_by_hand(schema, cell_size, before, after, kn, ratio) -> np.ndarray:
    """The cells with a free grain that moved and that no pair presses with a normal force above ``ratio`` times
    the cell's largest (linear law, f_n = kn overlap), one grain and one pair at a time."""
    out = np.zeros(cell_size.shape[0], dtype=bool)
    for c in range(cell_size.shape[0]):
        force = _pair_forces_by_hand(schema, cell_size[c], after[c], kn)
        largest = max(force.values())
        for grain in set(int(g) for g in schema.free_dofs[:, 0]):
            moved = any(after[c, k] != before[c, k] for k, (g, _) in enumerate(schema.free_dofs) if g == grain)
            pressed = any(f > ratio * largest for pair, f in force.items() if grain in pair)
            out[c] |= moved and not pressed
    return out


def _resting_by_hand(schema, cell_size, free, kn, ratio) -> np.ndarray:
    """bool (n, n_free): the free DOFs of the grains that no pair presses with a normal force above ``ratio`` times
    the cell's largest (linear law), one grain and one pair at a time."""
    out = np.zeros(free.shape, dtype=bool)
    for c in range(cell_size.shape[0]):
        force = _pair_forces_by_hand(schema, cell_size[c], free[c], kn)
        largest = max(force.values())
        for k, (grain, _) in enumerate(schema.free_dofs):
            out[c, k] = not any(f > ratio * largest for pair, f in force.items() if int(grain) in pair)
    return out


def _in_touch_with(schema, cell_size, free, grain, other, overlap) -> np.ndarray:
    """``free`` with ``grain`` moved beyond ``other`` on the line from the cell's centre through ``other``'s
    centre (clear of the other grains), overlapping ``other`` by ``overlap`` times r_i + r_j."""
    out = free.copy()
    cols = np.flatnonzero(schema.free_dofs[:, 0] == grain)
    for c in range(cell_size.shape[0]):
        x_other = schema.reference_position[other] * cell_size[c] / schema.reference_cell_size
        rsum = schema.radius[grain] + schema.radius[other]
        out[c, cols] = x_other + x_other / np.linalg.norm(x_other) * rsum * (1.0 - overlap)
    return out


def _hard_cases():
    data = np.load(HARD_CASES)
    return tuple(data[name] for name in ("cell_size", "free_position", "shear_force")), data["d_eps"]


def test_released_cells_are_those_with_a_grain_that_moved_and_that_nothing_presses():
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    schema, law = meso.schema(), ContactLaw()
    ratio = 1e-4
    released_cells = DemEscalation(meso, law, meso.contact_tolerance, force_ratio=ratio).released
    (size, free, shear), d_eps = _hard_cases()
    inc = FastAdvance(relaxing_network(), 20, ratio)(size, free, shear, d_eps)

    def released(after):
        return released_cells(inc.cell_size, free, after)

    assert not released_cells(inc.cell_size, inc.free_position, inc.free_position).any()  # none moved
    fine_grain = int(np.bincount(schema.free_dofs[:, 0]).argmax())
    fine = np.flatnonzero(schema.free_dofs[:, 0] == fine_grain)
    afloat = inc.free_position.copy()
    afloat[:, fine] = free[:, fine] + np.array([0.0, 0.0, 1e-9])  # back near the pore centre, a hair off its start
    pushed = inc.free_position.copy()
    pushed[:, fine[0]] += 0.2  # into the axial sphere
    centred = inc.free_position.copy()
    centred[:, fine] = 0.0  # at the pore centre: clear of every sphere of this cell
    touching = _in_touch_with(schema, inc.cell_size, inc.free_position, fine_grain, 0, 1e-13)  # only axial sphere 0
    pressed = _in_touch_with(schema, inc.cell_size, inc.free_position, fine_grain, 0, 1e-2)
    for after in (inc.free_position, afloat, pushed, centred, touching, pressed):
        expected = _released_by_hand(schema, inc.cell_size, free, after, law.kn, ratio)
        assert np.array_equal(released(after), expected)
    assert _released_by_hand(schema, inc.cell_size, free, centred, law.kn, ratio).sum() >= 3
    assert not released(pushed).any()
    assert released(touching).all()  # in touch at a round-off overlap: pushed by one sphere, held by none
    assert 0 < released(pressed).sum() < released(touching).sum()  # pressed: released only where a lateral sphere is


def test_resting_grains_are_those_that_nothing_presses_at_the_start():
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    schema, law = meso.schema(), ContactLaw()
    ratio = 1e-4
    escalation = DemEscalation(meso, law, meso.contact_tolerance, force_ratio=ratio)
    (size, free, shear), d_eps = _hard_cases()
    inc = FastAdvance(relaxing_network(), 20, ratio)(size, free, shear, d_eps)
    fine_grain = int(np.bincount(schema.free_dofs[:, 0]).argmax())
    touching = _in_touch_with(schema, inc.cell_size, inc.free_position, fine_grain, 0, 1e-13)
    pressed = _in_touch_with(schema, inc.cell_size, inc.free_position, fine_grain, 0, 1e-2)
    seen = np.zeros(2, dtype=bool)
    for cell_size, position in ((size, free), (inc.cell_size, inc.free_position), (inc.cell_size, touching),
                                (inc.cell_size, pressed)):
        got = escalation.resting_dofs(cell_size, position)
        assert np.array_equal(got, _resting_by_hand(schema, cell_size, position, law.kn, ratio))
        seen |= (got.any(), (~got).any())
    assert seen.all()  # both kinds of grain among the cases
    fine = schema.free_dofs[:, 0] == fine_grain
    assert escalation.resting_dofs(inc.cell_size, touching)[:, fine].all()
    untouched = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    start = np.tile(untouched.position[schema.free_dofs[:, 0], schema.free_dofs[:, 1]], (2, 1))
    assert escalation.resting_dofs(np.tile(untouched.cell_size, (2, 1)), start).all()  # a cell that carries no force


def test_sliding_cells_are_those_where_a_grain_free_along_every_axis_slides_on_a_pressed_contact():
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    schema, law = meso.schema(), ContactLaw()
    escalation = DemEscalation(meso, law, meso.contact_tolerance, sliding=True)
    (size, free, shear), _ = _hard_cases()
    fine = int(np.bincount(schema.free_dofs[:, 0]).argmax())  # the grain free along every axis
    fine_pairs = np.array([fine in (int(i), int(j)) for i, j in schema.pairs])
    ev = evaluate(schema, size, free, shear, law, meso.contact_tolerance)
    pressed = (ev["contact"] > 0) & (ev["normal_force"] > 0)
    wedged = pressed[:, fine_pairs].any(axis=1)
    assert 0 < wedged.sum() < wedged.size  # the fine grain is pressed in some hard cases, free in others
    pushed = shear.copy()
    pushed[:, fine_pairs] = 1e3 * np.abs(shear).max() + 1.0  # beyond the Coulomb cap: capped, sliding
    stuck = shear.copy()
    stuck[:, fine_pairs] = 0.0
    stuck[:, ~fine_pairs] = 1e3 * np.abs(shear).max() + 1.0  # the lateral spheres (free along t only) slide
    assert np.array_equal(escalation.sliding(size, free, pushed), wedged)
    assert not escalation.sliding(size, free, stuck).any()
    for c in range(size.shape[0]):  # the flag, pair by pair
        f_s = np.linalg.norm(ev["shear_force"][c], axis=-1)
        by_hand = any(pressed[c, p] and f_s[p] >= (1 - 1e-9) * law.mu * ev["normal_force"][c, p]
                      for p in np.flatnonzero(fine_pairs))
        assert escalation.sliding(size[c:c + 1], free[c:c + 1], shear[c:c + 1])[0] == by_hand
    released_only = DemEscalation(meso, law, meso.contact_tolerance)
    assert np.array_equal(released_only.escalated(size, free, free, pushed), released_only.released(size, free, free))
    assert np.array_equal(escalation.escalated(size, free, free, pushed), wedged)


def test_the_escalated_increment_is_the_dems_equilibrium_in_the_learning_state():
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    law = ContactLaw()
    (size, free, shear), d_eps = _hard_cases()
    new_size, new_free, new_shear, moment, area, converged = DemEscalation(meso, law, meso.contact_tolerance).advance(
        size, free, shear, d_eps)
    assert np.array_equal(new_size, size * (1.0 - d_eps))
    ev = evaluate(meso.schema(), new_size, new_free, new_shear, law, meso.contact_tolerance)
    assert np.array_equal(ev["shear_force"], new_shear)  # the learning state's springs: capped, zero out of contact
    largest = ev["normal_force"].max(axis=1)
    assert (np.abs(ev["unbalanced"]).max(axis=1) <= 1.0001 * DemSettings().force_tolerance * largest).all()
    scale = np.abs(moment).max(axis=(1, 2))[:, None, None]
    assert np.abs(ev["moment"].reshape(moment.shape) - moment).max() <= 1e-9 * scale.max()
    assert np.allclose(ev["area"], area, rtol=1e-12)
    assert converged.dtype == bool and converged.all()  # reported as n_escalated_unconverged where not


@pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")
def test_the_hybrid_takes_the_released_cells_again_from_rest_and_counts_them(monkeypatch):
    meso = mesostructure_arg("hcell3d:alpha0=55").build(None)
    hybrid = AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D, equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                       dem_escalation=True, release_rule=RELEASE_RULE_AFTER)
    assert AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D, equilibrium_corrections=2).escalation is None  # plain cell
    assert AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D, equilibrium_corrections=0).escalation is None
    state = hybrid.init_state(meso, 3)
    for _ in range(5):
        state, _ = hybrid.step(state, np.full((3, 3), 2e-4))
    d_eps = np.tile([1e-4, -5e-5, -5e-5], (3, 1))
    plain, plain_response = hybrid.step(state, d_eps)
    assert plain_response.diagnostics["n_released"] == 0  # the plain cell's grains stay in contact
    released = np.zeros((3, hybrid.arrays.schema.free_dofs.shape[0]), dtype=bool)
    released[1, :2] = True  # the detection is the tests above's; here: what follows it
    monkeypatch.setattr(hybrid.escalation, "released_dofs", lambda *args: released)
    out, response = hybrid.step(state, d_eps)
    assert response.diagnostics["n_released"] == 1 and response.diagnostics["n_escalated"] == 0
    again, _ = hybrid.fast.increment(*(np.asarray(a)[1:2] for a in state), d_eps[1:2], held=released[1:2])
    for whole, part in zip((*out, response.moment, response.area),
                           (again.cell_size, again.free_position, again.shear_force, again.moment, again.area)):
        assert np.array_equal(whole[1:2], part)
    for whole, kept in zip((*out, response.moment, response.area), (*plain, plain_response.moment, plain_response.area)):
        assert np.array_equal(whole[[0, 2]], np.asarray(kept)[[0, 2]])
    assert not np.array_equal(out.free_position[1], plain.free_position[1])  # another first guess, another balance
    # the step's counts are those of the cells as they end: cells 0 and 2 of the first pass, cell 1 of the pass again
    # (its Newton steps added to the first pass's)
    first, _ = hybrid.fast.increment(*state, d_eps)
    first_corrections = hybrid.fast.last_corrections()
    again, _ = hybrid.fast.increment(*(np.asarray(a)[1:2] for a in state), d_eps[1:2], held=released[1:2])
    again_corrections = hybrid.fast.last_corrections()
    ratio = first_corrections.force_ratio[1].copy()
    ratio[1] = again_corrections.force_ratio[1, 0]
    d = response.diagnostics
    assert d["force_ratio_max"] == ratio.max() and d["n_unconverged"] == np.count_nonzero(ratio > 1e-3)
    assert d["n_corrections"] == first_corrections.steps.sum() + again_corrections.steps.sum()
    for name, flag in (("n_coulomb_capped", "capped"), ("n_tension_clipped", "opened"), ("n_mechanism", "mechanism")):
        ends = getattr(first, flag).copy()
        ends[1] = getattr(again, flag)[0]
        assert d[name] == np.count_nonzero(ends), name
    # every cell taken again: the force ratios are the pass again's alone
    everywhere = np.zeros_like(released)
    everywhere[:, :2] = True
    monkeypatch.setattr(hybrid.escalation, "released_dofs", lambda *args: everywhere)
    _, response = hybrid.step(state, d_eps)
    hybrid.fast.increment(*state, d_eps, held=everywhere)
    again_corrections = hybrid.fast.last_corrections()
    assert response.diagnostics["force_ratio_max"] == again_corrections.force_ratio[1].max()
    assert again_corrections.force_ratio[1].max() != first_corrections.force_ratio[1].max()


@pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")
def test_the_hybrid_starts_the_resting_grains_at_rest_and_takes_again_the_cells_released_beyond_them(monkeypatch):
    meso = mesostructure_arg("hcell3d:alpha0=55").build(None)
    hybrid = AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D, equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                       dem_escalation=True)
    assert hybrid.release_rule == RELEASE_RULE  # no certificate of a rule: this package's
    state = hybrid.init_state(meso, 3)
    for _ in range(5):
        state, _ = hybrid.step(state, np.full((3, 3), 2e-4))
    d_eps = np.tile([1e-4, -5e-5, -5e-5], (3, 1))
    n_free = hybrid.arrays.schema.free_dofs.shape[0]
    resting, released = np.zeros((3, n_free), dtype=bool), np.zeros((3, n_free), dtype=bool)
    resting[0, 0] = resting[2, 0] = True
    released[0, 0] = True  # started at rest, pushed and released: the rule's end, not taken again
    released[1, :2] = True  # released, none resting: taken again with them at rest
    released[2, 1] = True  # released beyond its resting grain: taken again with both at rest
    monkeypatch.setattr(hybrid.escalation, "resting_dofs", lambda *args: resting)
    monkeypatch.setattr(hybrid.escalation, "released_dofs",
                        lambda size, *args: released if len(size) == 3 else np.zeros((len(size), n_free), dtype=bool))
    out, response = hybrid.step(state, d_eps)
    d = response.diagnostics
    assert (d["n_released"], d["n_resting"], d["n_released_pushed"], d["n_escalated"]) == (3, 2, 1, 0)
    plain, _ = hybrid.fast.increment(*state, d_eps)
    for c, held in ((0, resting[0]), (1, released[1]), (2, resting[2] | released[2])):
        again, _ = hybrid.fast.increment(*(np.asarray(a)[c:c + 1] for a in state), d_eps[c:c + 1], held=held[None])
        for whole, part in zip((*out, response.moment, response.area),
                               (again.cell_size, again.free_position, again.shear_force, again.moment, again.area)):
            assert np.array_equal(whole[c:c + 1], part)
        assert not np.array_equal(out.free_position[c], plain.free_position[c])  # another first guess, another balance


@pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")
def test_off_cpu_the_hybrid_with_a_release_rule_is_not_certified(tmp_path):
    """The released-grain rules run on the compiled CPU path only; on another device (torch's meta device here)
    a released cell takes the DEM's increment, which the certificate did not measure: certificate_problem says so."""
    import json  # noqa: PLC0415
    import shutil  # noqa: PLC0415

    for path in SHIPPED_3D.parent.glob(f"{SHIPPED_3D.stem}*"):
        shutil.copy(path, tmp_path / path.name)
    meta = tmp_path / f"{SHIPPED_3D.stem}.json"
    record = json.loads(meta.read_text())
    record["certificate"]["settings"].update(equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                                             dem_escalation=True, dem_escalation_rule=RELEASE_RULE)
    meta.write_text(json.dumps(record))
    cells = {device: AnnCell3D(ContactLaw(), 0.5, model=tmp_path / SHIPPED_3D.name, equilibrium_corrections=2,
                               equilibrium_tolerance=1e-3, dem_escalation=True, device=device) for device in ("cpu", "meta")}
    assert cells["cpu"].certificate_problem is None
    assert "runs on CPU only" in cells["meta"].certificate_problem


def test_a_certificate_counts_the_released_grains_where_the_hybrid_reports_them():
    """The certificate's tally sums n_released / n_released_pushed of a hybrid with the released-grain rule
    and records no such key for a hybrid without it (its certificate stays as it was)."""
    from types import SimpleNamespace

    from homogenization.learning.certificate import _Counter

    base = {"n_corrected": 1.0, "force_ratio_network_max": 0.1, "force_ratio_max": 0.01}
    plain = _Counter(SimpleNamespace(name="ann"))
    plain._tally(base)
    assert "n_released" not in plain.corrections and "n_released_pushed" not in plain.corrections
    hybrid = _Counter(SimpleNamespace(name="ann"))
    hybrid._tally({**base, "n_released": 3.0, "n_released_pushed": 1.0})
    hybrid._tally({**base, "n_released": 2.0, "n_released_pushed": 0.0})
    assert hybrid.corrections["n_released"] == 5 and hybrid.corrections["n_released_pushed"] == 1


def test_again_at_rest_is_the_increment_with_those_grains_held_without_the_network():
    """``FastAdvance.again_at_rest`` reuses the last call's first guess: bit for bit the cells of
    ``increment(..., held=...)`` (state, moment, flags, corrections), whatever cells are taken again."""
    (size, free, shear), d_eps = _hard_cases()
    fast = FastAdvance(relaxing_network(), 20, 1e-6)
    fast(size, free, shear, d_eps)
    index = np.array([0, 2, 3])
    held = np.zeros((index.size, free.shape[1]), dtype=bool)
    held[:, -3:] = True  # the fine grain
    held[1, 0] = True
    got = fast.again_at_rest(index, held)
    got_counts = fast.last_corrections()
    expected = fast.increment(size[index], free[index], shear[index], d_eps[index], held=held)[0]
    for name, value in expected._asdict().items():
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(value), err_msg=name)
    for name, value in fast.last_corrections()._asdict().items():
        np.testing.assert_array_equal(getattr(got_counts, name), value, err_msg=name)
    assert got_counts.steps.sum() > 0
    assert not np.array_equal(np.asarray(got.free_position), fast(size[index], free[index], shear[index],
                                                                 d_eps[index]).free_position)  # another first guess
