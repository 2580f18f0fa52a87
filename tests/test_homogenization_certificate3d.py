"""The certificate of a 3D meso-ANN: triaxial tests against the DEM, 3D rollouts, the cell's spin period."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from homogenization.learning import certificate
from homogenization.element_test import programme as programmes
from homogenization.ann import default_model_path
from training import rollout
from warp_hcell.core.provenance import file_sha256
from warp_hcell.mesostructures.builders import mesostructure_arg

SHIPPED_3D = default_model_path(3)
needs_model = pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")

SHORT = {"pressures": (2e5,), "eps_max": 0.02, "spatial_rule": (5, 2), "rollout": False}
"""A reduced 3D certificate: one pressure, 2 % strain, Lebedev order 5 x 2 spins = 14 cells."""


def _cell(spec: str):
    return mesostructure_arg(spec).build(None)


def test_spatial_tests_are_the_triaxial_tests_in_both_senses():
    tests = certificate.tests_of(dim=3)
    names = [info["name"] for info, _ in tests]
    assert len(names) == 4 * len(certificate.PRESSURES) + 1 and names[-1] == "undrained reversal p0=200000"
    assert names[:4] == ["undrained compression p0=200000", "undrained extension p0=200000",
                         "drained compression p0=200000", "drained extension p0=200000"]
    for info, programme in tests:
        assert programmes.dimension(programme) == 3 and programme[0].stop_at_p == info["p0"]
        shear = programme[1]
        sign = -1.0 if info["sense"] == "extension" else 1.0
        assert math.isclose(shear.target[0], sign * certificate.EPS_MAX / (2 if info["sense"] == "reversal" else 1))
        if info["kind"] == "undrained":  # isochoric increments: (1 - d1)(1 - d2)(1 - d3) = 1
            d = np.array(shear.target) / shear.n_increments
            assert shear.control == ("strain",) * 3 and abs(np.prod(1.0 - d) - 1.0) < 1e-15
        else:  # the lateral stresses held at p0
            assert shear.control == ("strain", "stress", "stress") and shear.target[1:] == (info["p0"], info["p0"])
    reverse = tests[-1][1][2]
    assert reverse.label == "reverse" and math.isclose(reverse.target[0], -certificate.EPS_MAX)
    assert certificate.requested_settings(3)["spatial_rule"] == list(certificate.SPATIAL_RULE)
    assert "n_orientations" not in certificate.requested_settings(3)


def test_rollout_legs_of_both_dimensions():
    """Constant-volume legs keep the cell's volume to first order (trace 0) in 2D and 3D; the planar
    legs are the biaxial ones (cos 2 theta, -cos 2 theta) and (c^2 - s^2/2, s^2 - c^2/2)."""
    for dim in (2, 3):
        paths = rollout.held_out_paths(dim)
        assert all(p.direction.shape == (dim,) for p in paths)
        for p in paths:
            trace = p.direction.sum()
            expected = 0.0 if p.kind == "constant-volume" else 0.5  # drained: volumetric rate half the axial
            assert abs(trace - expected) < 1e-15, (dim, p)
    for p in rollout.held_out_paths(2):
        c, s = math.cos(math.radians(p.theta_deg)), math.sin(math.radians(p.theta_deg))
        expected = ([c * c - s * s, s * s - c * c] if p.kind == "constant-volume"
                    else [c * c - 0.5 * s * s, s * s - 0.5 * c * c])
        np.testing.assert_array_equal(p.direction, expected)
    axial = next(p for p in rollout.held_out_paths(3) if p.theta_deg == 0.0 and p.kind == "constant-volume")
    np.testing.assert_array_equal(axial.direction, [1.0, -0.5, -0.5])


@pytest.mark.parametrize("spec, period", [
    ("hcell3d:alpha0=55", 90.0),
    ("hcell3d:alpha0=55,lateral=0.9", 90.0),                    # both planes alike: still four-fold
    ("hcell3d-fines:alpha0=55,ratio=0.9", 90.0),                # a fine grain at the centre
    ("hcell3d-fines:alpha0=55,ratio=0.5,n=0.2", 90.0),          # on the axis
    ("hcell3d:alpha0=60,plane=80", 180.0),                      # planes not orthogonal: a half turn only
    ("hcell3d-fines:alpha0=55,ratio=0.5,t1=0.1", 360.0),        # off the axis: no turn maps the cell
])
def test_spin_period_is_read_from_the_cell(spec, period):
    assert _cell(spec).spin_period_deg() == period


def test_spin_period_of_a_planar_cell_is_an_error():
    with pytest.raises(ValueError, match="spatial cells only"):
        _cell("hcell:alpha0=55").spin_period_deg()


def _copy(folder: Path) -> Path:
    folder.mkdir()
    for suffix in (".pt", ".json"):
        shutil.copy(SHIPPED_3D.with_suffix(suffix), folder / f"m{suffix}")
    shutil.copy(SHIPPED_3D.with_name(f"{SHIPPED_3D.stem}_ood.npz"), folder / "m_ood.npz")
    return folder / "m.pt"


@needs_model
def test_the_shipped_3d_model_carries_a_passed_certificate_of_its_file():
    meta = json.loads(SHIPPED_3D.with_suffix(".json").read_text())
    cert = meta["certificate"]
    assert cert["passed"] and cert["model_sha256"] == file_sha256(SHIPPED_3D)
    assert cert["settings"]["spatial_rule"] == list(certificate.SPATIAL_RULE) and cert["settings"]["staggered_spins"]
    assert len(cert["tests"]) == 4 * len(certificate.PRESSURES) + 1 and cert["worst"] <= certificate.TARGET
    assert not cert["revision"].endswith("-dirty")


@needs_model
def test_the_shipped_3d_model_passes_a_short_certificate_and_a_perturbed_one_fails(tmp_path):
    model = _copy(tmp_path / "shipped")
    cert = certificate.certify(model, **SHORT)
    figures = np.array([[t.dp, t.dq] for t in cert.tests])
    assert len(cert.tests) == 5 and np.all(figures > 0) and np.all(figures < 0.01)  # measured 0.04-0.43 %
    assert cert.within_target and cert.settings["n_cells"] == 14
    assert cert.verdict == "weak" and not cert.passed  # below the minimum certificate: not passed
    assert cert.envelope["kinds"] == ["drained", "undrained"] and cert.envelope["pressures"] == [2e5, 2e5]
    assert cert.coverage["fraction_within"] > 0.95

    state = torch.load(model, weights_only=True)
    state["rate_mean"] = state["rate_mean"] + 4.0 * state["rate_std"]  # 2 standard deviations still pass (1.7 %)
    torch.save(state, model)
    bad = certificate.certify(model, **SHORT)
    assert not bad.passed and bad.worst > certificate.TARGET


@needs_model
def test_the_3d_rollout_of_the_shipped_model_follows_the_dem():
    """Single ten-sphere cells along the held-out legs (two precompressions, three axes, undrained and
    drained), 2e-3 increments so that the test stays short: a model returning the touching
    cell's zero moment would score 1."""
    from training.checkpoint import load_checkpoint, read_metadata
    from warp_hcell.core.parameters import ContactLaw, DemSettings
    from warp_hcell.mesostructures.files import from_description

    net, _ = load_checkpoint(SHIPPED_3D)
    meta = read_metadata(SHIPPED_3D)
    report = rollout.rollout_report(net, from_description(meta["mesostructure"]), ContactLaw.from_dict(meta["contact_law"]),
                                    DemSettings(contact_tolerance=float(meta["contact_tolerance"])), increments=(2e-3,))
    errors = report["increment_0.002"]["per_path"]
    assert len(errors) == 12 and max(errors) < 0.02


def test_a_round_of_active_learning_probes_the_3d_states_of_the_failing_tests(tmp_path):
    """The rounds of homogenization.learning.active on a 3D database: the certificate's triaxial tests keep
    their DEM states (3 components per grain, a spring vector per pair), the failing ones are probed
    and appended, and the model is retrained and certified again on the spatial rule."""
    import h5py

    from homogenization.learning import active
    from homogenization.learning.settings import CertificateSettings
    from test_database_dimension import SPATIAL, tiny_database
    from training import train as training_train
    from training.config import TrainConfig
    from warp_hcell.database.format import ACTIVE_GROUP

    db = tiny_database(tmp_path / "db.h5", SPATIAL)
    model = tmp_path / "m.pt"
    args = ["--epochs", "8", "--hidden", "12", "--threads", "1", "--no-rollout", "-q"]
    assert training_train.main(["--data", str(db), "--out", str(model), *args]) == 0
    short = {"pressures": (2e5,), "eps_max": 0.01, "spatial_rule": (3, 1), "rollout": False, "target": 1e-6}
    config = TrainConfig(epochs=8, hidden=(12,), threads=1, rollout=False)
    rounds, _ = active.learn(db, model, config, settings=active.ActiveSettings(rounds=1, samples_per_round=400),
                             certify_settings=CertificateSettings(**short), log=lambda *lines: None)
    assert [r.round for r in rounds] == [0, 1] and rounds[1].samples_added == 400
    assert set(rounds[1].tests) <= {info["name"] for info, _ in certificate.tests_of((2e5,), 0.01, dim=3)}
    cert = json.loads(model.with_suffix(".json").read_text())["certificate"]
    assert cert["settings"]["spatial_rule"] == [3, 1] and cert["settings"]["n_cells"] == 3
    with h5py.File(db) as f:
        assert np.count_nonzero(f["source_round"][()] == 1) == 400
        assert f[f"{ACTIVE_GROUP}/cell_size"].shape[1] == 3
        assert f[f"{ACTIVE_GROUP}/shear_force"].shape[1:] == (SPATIAL.n_pairs, 3)
