"""``RELEASE_RULE_DRAG``: a grain that started the corrections at rest and that a neighbour pushed lightly is
relaxed as the DEM relaxes it from rest (``homogenization.ann.relaxation``, ``DemEscalation.relaxed``), so the
friction of the pushing contact drags it; the hybrid takes that end for those cells only, and a certificate of
the rule covers that rule only."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from model_copies import shipped_3d_copy

from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell3D, AnnState
from homogenization.ann.escalation import DemEscalation, RELEASE_RULE, RELEASE_RULE_AFTER, RELEASE_RULE_DRAG
from homogenization.ann.relaxation import relax
from homogenization.cli import certify as certify_cli
from homogenization.learning.certificate import requested_settings
from training import fast_model
from warp_hcell.core.cli import UserError
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.database.learning_state import positions
from warp_hcell.mesostructures.builders import mesostructure_arg

ROOT = Path(__file__).resolve().parents[1]
LARGE_AXIAL = ROOT / "benchmarks" / "cells" / "large_axial.toml"
HARD_CASES = ROOT / "tests" / "data" / "equilibrium" / "large_axial_hard.npz"
SHIPPED_3D = default_model_path(3)
needs_model = pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")


def _pusher_and_grain(mu: float, tangential: float, normal: float = 1e-5):
    """The free sphere (grain 1, radius 0.5 m) touching a driven one (grain 0) with zero force, after the driven
    one moved ``normal`` [m] towards it and ``tangential`` [m] across: (its displacement (3,) [m], substeps)."""
    law = ContactLaw()
    radius = np.array([0.5, 0.5])
    x0 = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    x1 = x0.copy()
    x1[0, 0] = [normal, tangential, 0.0]
    simulated = np.zeros((1, 2, 3), dtype=bool)
    simulated[0, 1] = True
    mass = DemSettings().density * 4.0 / 3.0 * math.pi * radius ** 3
    dt = DemSettings().dt_factor * math.sqrt(mass.min() / law.kn)
    out, substeps = np.empty_like(x0), np.empty(1, dtype=np.int64)
    relax(x0, x1, simulated, np.zeros((1, 1, 3)), np.array([[0, 1]]), radius, 1.0 / mass, dt, law.kn, law.kt, mu,
          1e-9, DemSettings().damping, np.array([100]), np.array([law.kn * abs(normal)]), 1e-6, 20_000,
          np.array([[False] * 3, [True] * 3]), out, substeps)
    return out[0, 1] - x0[0, 1], int(substeps[0])


def test_a_pushed_grain_is_dragged_by_the_friction_of_the_pushing_contact():
    push = 1e-5
    frictionless, _ = _pusher_and_grain(mu=0.0, tangential=push)
    assert frictionless[0] == pytest.approx(push, rel=0.01)  # pushed along the normal as far as the pusher went
    assert abs(frictionless[1]) < 1e-3 * push  # only the turn of the normal, 1e-5 rad, moves it across
    for mu in (0.1, 0.3):  # kt / kn = 0.5 > mu: the contact slides, its tangential force mu times the normal one
        sliding, _ = _pusher_and_grain(mu=mu, tangential=push)
        assert sliding[1] == pytest.approx(mu * sliding[0], rel=0.02) and sliding[2] == 0.0
    sticking, _ = _pusher_and_grain(mu=10.0, tangential=push)  # dragged until the grain leaves the pusher
    assert 0.5 * push < sticking[1] < push
    away, substeps = _pusher_and_grain(mu=10.0, tangential=push, normal=-push)  # the pusher leaves: nothing pushes it
    assert np.array_equal(away, np.zeros(3)) and substeps == 100  # held at rest, as the DEM holds an unloaded grain


def test_the_relaxed_fine_grain_lands_where_the_dem_from_rest_puts_it():
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    data = np.load(HARD_CASES)
    size, free, shear, d_eps = (data[k] for k in ("cell_size", "free_position", "shear_force", "d_eps"))
    escalation = DemEscalation(meso, ContactLaw(), meso.contact_tolerance)
    dem_size, dem_free, *_ = escalation.advance(size, free, shear, d_eps)
    fine = meso.schema().free_dofs[:, 0] == meso.radius.size - 1
    pushed = np.tile(fine, (size.shape[0], 1))
    x0, x1 = positions(escalation.schema, size, free), positions(escalation.schema, dem_size, dem_free)
    x1[:, -1] = x0[:, -1]  # the fine grain where it started: the others at the DEM's end
    moved = np.linalg.norm((dem_free - free)[:, fine], axis=1)  # 14 mm (a snap) and 69 um (a push)
    out, substeps = escalation.relaxed(x0, x1, shear, d_eps, pushed)
    assert np.array_equal(out[:, ~fine], dem_free[:, ~fine])  # the other grains keep their given end
    assert (np.linalg.norm((out - dem_free)[:, fine], axis=1) <= 0.1 * moved).all()  # measured: within 3 %
    assert (substeps < 20_000).all()
    frictionless = DemEscalation(meso, ContactLaw(phi_g_deg=1e-6), meso.contact_tolerance)
    off, _ = frictionless.relaxed(x0, x1, shear, d_eps, pushed)
    assert (np.linalg.norm((off - dem_free)[:, fine], axis=1) > moved).all()  # without the drag: far off


@needs_model
def test_the_hybrid_relaxes_the_pushed_grains_only_and_counts_them(monkeypatch):
    meso = mesostructure_arg("hcell3d:alpha0=55").build(None)
    cells = {rule: AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D, equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                             dem_escalation=True, release_rule=rule) for rule in (RELEASE_RULE, RELEASE_RULE_DRAG)}
    state = cells[RELEASE_RULE].init_state(meso, 3)
    for _ in range(5):
        state, _ = cells[RELEASE_RULE].step(state, np.full((3, 3), 2e-4))
    d_eps = np.tile([1e-4, -5e-5, -5e-5], (3, 1))
    n_free = cells[RELEASE_RULE].arrays.schema.free_dofs.shape[0]
    resting, released = np.zeros((3, n_free), dtype=bool), np.zeros((3, n_free), dtype=bool)
    resting[0, 0] = resting[2, 0] = True
    released[0, 0] = True  # started at rest, pushed and released: relaxed under the drag rule
    released[1, :2] = True  # released, none resting: taken again at rest, not relaxed
    outs = {}
    for rule, cell in cells.items():
        monkeypatch.setattr(cell.escalation, "resting_dofs", lambda *args: resting)
        monkeypatch.setattr(cell.escalation, "released_dofs",
                            lambda size, *args: released.copy() if len(size) == 3 else np.zeros((len(size), n_free), dtype=bool))
        outs[rule] = cell.step(state, d_eps)
    (plain, plain_response), (out, response) = outs[RELEASE_RULE], outs[RELEASE_RULE_DRAG]
    assert response.diagnostics["n_relaxed"] == 1 and response.diagnostics["n_relaxed_substeps"] > 0
    assert "n_relaxed" not in plain_response.diagnostics
    for whole, kept in zip((*out, response.moment, response.area), (*plain, plain_response.moment, plain_response.area)):
        assert np.array_equal(whole[1:], np.asarray(kept)[1:])  # bit for bit the earlier rule's
    schema = cells[RELEASE_RULE_DRAG].arrays.schema
    expected, _ = cells[RELEASE_RULE_DRAG].escalation.relaxed(
        fast_model.positions(schema, state.cell_size[:1], state.free_position[:1]),
        fast_model.positions(schema, plain.cell_size[:1], plain.free_position[:1]), state.shear_force[:1], d_eps[:1],
        resting[:1])
    assert np.array_equal(out.free_position[:1], expected)
    assert out.free_position[0, 0] != plain.free_position[0, 0]
    again = cells[RELEASE_RULE_DRAG].response(AnnState(*(np.asarray(a)[:1] for a in out)))
    assert np.allclose(again.moment, response.moment[:1], rtol=1e-12, atol=0.0)  # the contact law at its end state


@needs_model
def test_a_certificate_of_the_drag_rule_covers_that_rule_only(tmp_path):
    model, meta = shipped_3d_copy(tmp_path)
    meta["certificate"]["settings"].update(requested_settings(3, equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                                                              dem_escalation=True, release_rule=RELEASE_RULE_DRAG))
    model.with_suffix(".json").write_text(json.dumps(meta))
    cell = AnnCell3D(ContactLaw(), 0.5, model=model, dem_escalation=True)
    assert cell.release_rule == RELEASE_RULE_DRAG and cell.certificate_problem is None
    for other in (RELEASE_RULE, RELEASE_RULE_AFTER):
        problem = AnnCell3D(ContactLaw(), 0.5, model=model, dem_escalation=True, release_rule=other).certificate_problem
        assert problem is not None and "by another rule" in problem
    assert requested_settings(3, equilibrium_corrections=2, equilibrium_tolerance=1e-3,
                              dem_escalation=True)["dem_escalation_rule"] == RELEASE_RULE  # the default unchanged


@needs_model
def test_certify_refuses_the_drag_rule_for_the_network_alone():
    with pytest.raises(UserError, match="--release-rule drag"):
        certify_cli.main(["--model", str(SHIPPED_3D), "--equilibrium-corrections", "0", "--release-rule", "drag"])


def test_the_certificate_settings_carry_the_rule_to_certify_and_refuse_it_for_the_network_alone():
    from homogenization.learning.settings import CertificateSettings

    assert CertificateSettings().keywords()["release_rule"] == RELEASE_RULE
    drag = CertificateSettings(equilibrium_corrections=20, equilibrium_tolerance=1e-4, release_rule="drag")
    assert drag.keywords()["release_rule"] == RELEASE_RULE_DRAG
    with pytest.raises(ValueError, match="a rule of the hybrid"):
        CertificateSettings(release_rule="drag")
    with pytest.raises(ValueError, match="one of resting, drag"):
        CertificateSettings(equilibrium_corrections=20, release_rule="after")


@pytest.mark.parametrize("command", ["train", "learn"])
def test_train_and_learn_refuse_the_drag_rule_for_the_network_alone_in_one_line(command, tmp_path, capsys):
    from homogenization.cli import hmodel

    argv = (["train", "--data", str(tmp_path / "none.h5"), "--out", str(tmp_path / "m.pt")] if command == "train"
            else ["learn", "--mesostructure", "hcell:alpha0=55", "--out", str(tmp_path / "run")])
    assert hmodel.main([*argv, "--equilibrium-corrections", "0", "--release-rule", "drag"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--release-rule drag: a rule of the hybrid" in err[0]
    assert not any(tmp_path.iterdir())


def test_a_certificate_of_another_rule_is_not_current_for_the_loop(tmp_path):
    """``hmodel learn`` measures again a model whose certificate ran the hybrid under another released-grain rule."""
    import dataclasses

    from homogenization.ann.records import Certificate
    from homogenization.learning.active import _current
    from homogenization.learning.settings import CertificateSettings
    from warp_hcell.core.provenance import file_sha256

    model = tmp_path / "m.pt"
    model.write_bytes(b"weights")
    measured = CertificateSettings(equilibrium_corrections=20, equilibrium_tolerance=1e-4, release_rule="drag")
    settings = requested_settings(3, pressures=measured.pressures, eps_max=measured.eps_max,
                                  n_orientations=measured.n_orientations, spatial_rule=measured.spatial_rule,
                                  equilibrium_corrections=20, equilibrium_tolerance=1e-4, dem_escalation=True,
                                  release_rule=RELEASE_RULE_DRAG)
    cert = Certificate(target=measured.target, worst=0.01, worst_test="", metric="", tests=(), rollout=None,
                       coverage=None, dem_spread=None, settings=settings, cell_parameters={},
                       model_sha256=file_sha256(model), revision="", seconds=0.0, within_target=True, below_minimum=[],
                       verdict="passed", passed=True)
    assert _current(cert, model, measured, 3)
    resting = dataclasses.replace(cert, settings={**settings, "dem_escalation_rule": RELEASE_RULE})
    assert not _current(resting, model, measured, 3)
    assert _current(resting, model, dataclasses.replace(measured, release_rule="resting"), 3)
