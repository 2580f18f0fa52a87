"""The meso-ANN certificate (homogenization.learning.certificate) and the refusal of models without a passed one."""

import dataclasses
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from homogenization.learning import certificate
from homogenization.ann.records import Certificate, Round
from homogenization.ann import default_model_path
from homogenization.cli import biaxial, certify
from training.card import read_card
from warp_hcell.core.cli import run_main
from warp_hcell.core.provenance import file_sha256

pytestmark = pytest.mark.skipif(not default_model_path().is_file(), reason="default model not installed")

SHORT = {"pressures": (2e5,), "eps_max": 0.02, "n_orientations": 6, "rollout": False}
"""A reduced certificate (the constants are the full one): one pressure, 2 % strain, 6 orientations."""
RUN = ["--backend", "ann", "--p0", "2e5", "--eps-max", "0.002", "--increment", "1e-4", "--orientations", "4"]


def _copy_shipped(folder: Path) -> Path:
    folder.mkdir()
    source = default_model_path()
    for suffix in (".pt", ".json"):
        shutil.copy(source.with_suffix(suffix), folder / f"m{suffix}")
    shutil.copy(source.with_name(f"{source.stem}_ood.npz"), folder / "m_ood.npz")
    return folder / "m.pt"


def _perturb(model: Path, shift: float) -> None:
    """Shift the network's mean free-DOF rate by ``shift`` of its spread (scaling the rates by 1.5
    instead is repaired by the learned relaxation: the model still passes)."""
    state = torch.load(model, weights_only=True)
    state["rate_mean"] = state["rate_mean"] + shift * state["rate_std"]
    torch.save(state, model)


@pytest.fixture(scope="module")
def shipped_copy(tmp_path_factory):
    return _copy_shipped(tmp_path_factory.mktemp("cert") / "shipped")


@pytest.fixture(scope="module")
def short_certificate(shipped_copy):
    return certificate.certify(shipped_copy, **SHORT)


def test_the_shipped_model_is_within_the_target_of_the_short_certificate_which_is_not_passed(short_certificate,
                                                                                              shipped_copy):
    """A certificate weaker than the minimum (one pressure, 2 %, 6 orientations, no rollouts) is
    not passed, however small its figures; its envelope is what it ran."""
    cert = short_certificate
    assert [t.name for t in cert.tests] == [
        "constant-volume compression p0=200000",
        "drained compression p0=200000", "drained extension p0=200000", "constant-volume reversal p0=200000"]
    figures = np.array([[t.dp, t.dq] for t in cert.tests])
    assert np.all(figures > 0) and np.all(figures < 0.01)  # measured 0.03-0.39 % against the DEM
    assert cert.within_target and cert.worst == figures.max()
    assert not cert.passed and cert.verdict == "weak" and len(cert.below_minimum) == 4
    assert cert.below_minimum[:2] == ["pressures 200000 (minimum: 200000, 1e+06)", "eps_max 0.02 (minimum 0.1)"]
    assert cert.envelope["pressures"] == [2e5, 2e5] and cert.envelope["eps_max"] == 0.02
    assert cert.envelope["kinds"] == ["constant-volume", "drained"]
    assert cert.envelope["cell_parameters"] == {"alpha0_deg": 55.0}
    assert cert.model_sha256 == file_sha256(shipped_copy)
    assert all(t.scale >= t.p0 for t in cert.tests)
    assert all(0 <= t.dem_spread < 0.002 for t in cert.tests)  # the DEM from rest: measured 0.03-0.05 %
    assert cert.coverage["fraction_within"] > 0.95 and cert.coverage["n_states"] > 0


def test_a_perturbed_model_fails_the_certificate(tmp_path):
    model = _copy_shipped(tmp_path / "bad")
    _perturb(model, 2.0)
    cert = certificate.certify(model, **SHORT)
    assert not cert.passed and cert.worst > certificate.TARGET


def _write(model: Path, cert: Certificate) -> None:
    certificate.write_certificate(model, cert)
    assert json.loads(model.with_suffix(".json").read_text())["certificate"]["model_sha256"] == cert.model_sha256


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_a_certified_model_runs_and_the_summary_and_run_say_so(tmp_path, capsys):
    model = _copy_shipped(tmp_path / "ok")  # with the shipped certificate of its file
    out = tmp_path / "run"
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "certificate passed (worst" in printed.out and "envelope" not in printed.out + printed.err
    with h5py.File(out / "run.h5") as f:
        ann = json.loads(f.attrs["parameters"])["ann_model"]
    shipped = json.loads(model.with_suffix(".json").read_text())["certificate"]
    assert ann["certified"] and ann["certificate_worst"] == shipped["worst"]
    assert ann["outside_envelope"] == [] and ann["envelope"]["pressures"] == [2e5, 1e6]


@pytest.mark.parametrize("dim", [2, 3])
def test_the_shipped_model_files_round_trip_byte_for_byte_through_their_records(dim):
    """The file-format guarantee: read as records and written as the package writes them, a shipped
    model's JSON is the same bytes (as a ``ModelCard``; its certificate as a ``Certificate``, its rounds as
    ``Round``s)."""
    path = default_model_path(dim).with_suffix(".json")
    text = path.read_text()
    meta = json.loads(text)
    meta["certificate"] = Certificate.from_dict(meta["certificate"]).to_dict()
    if "active_learning" in meta:  # the 2D model's rounds: the older, shorter record
        meta["active_learning"] = [Round.from_dict(r).to_dict() for r in meta["active_learning"]]
    assert json.dumps(meta, indent=2, sort_keys=True) + "\n" == text
    assert json.dumps(read_card(path).to_dict(), indent=2, sort_keys=True) + "\n" == text  # the model card


def test_a_round_writes_back_what_it_read_and_its_training_with_warm_start_null():
    shipped = {"passed": False, "round": 0, "samples_added": 0, "samples_total": 10, "seconds": 1.5, "worst": 0.1,
               "worst_test": "t"}
    assert Round.from_dict(shipped).to_dict() == shipped
    trained = {**shipped, "hidden": [16], "epochs": 3, "train_seconds": 2.0, "warm_start": None}
    assert Round.from_dict(trained).to_dict() == trained
    with pytest.raises(ValueError, match="^Round: unknown key 'extra'$"):
        Round.from_dict({**shipped, "extra": 1})


def test_the_shipped_certificates_meet_the_minimum_and_record_their_envelope():
    """Derived from their recorded settings and tests: p0 2e5 to 1e6, +-10 % axial strain."""
    from homogenization.ann.envelope import envelope_of, shortfalls, verdict

    for dim in (2, 3):
        path = default_model_path(dim)
        if not path.is_file():
            continue
        cert = Certificate.from_dict(json.loads(path.with_suffix(".json").read_text())["certificate"])
        assert shortfalls(cert, dim) == [] and verdict(cert) == "passed" == cert.verdict
        # the recorded envelope is the one its settings and tests give (with each test's kind, sense and p0)
        derived = envelope_of(dataclasses.replace(cert, envelope=None))
        assert cert.envelope == {k: v for k, v in derived.items() if k != "tests"}
        assert envelope_of(cert)["tests"] == derived["tests"] == sorted(
            [t.kind, t.sense, float(t.p0)] for t in cert.tests)
        stored = cert.envelope
        assert stored["pressures"] == [2e5, 1e6] and stored["eps_max"] == 0.1
        assert stored["kinds"] == (["constant-volume", "drained"] if dim == 2 else ["drained", "undrained"])


def test_a_run_below_the_envelope_warns_once_and_run_h5_records_it(tmp_path, capsys):
    """The shipped model at p0 = 5e4 N/m, below its certificate's lowest pressure (2e5), drained
    to 11 % (beyond its 10 %) in increments of 1e-2 (coarser than its 1e-4): one warning line, the status line
    and run.h5 say so."""
    model = _copy_shipped(tmp_path / "env")
    out = tmp_path / "low"
    argv = ["--backend", "ann", "--p0", "5e4", "--eps-max", "0.11", "--increment", "1e-2", "--orientations", "4",
            "--drained", "--model", str(model), "--out", str(out)]
    assert run_main(biaxial.main, argv) == 0
    printed = capsys.readouterr()
    warnings = [line for line in printed.err.splitlines() if "envelope" in line]
    assert warnings == ["warning: ann: the run is outside its certificate's envelope: p0 = 50000 N/m below the "
                        "lowest certified pressure 200000 N/m; axial strain 0.11 beyond the certified 0.1; axial "
                        "strain increment 0.01 coarser than the certified 0.0001"]
    assert "OUTSIDE its certificate's envelope" in printed.out
    with h5py.File(out / "run.h5") as f:
        ann = json.loads(f.attrs["parameters"])["ann_model"]
    assert ann["certified"] and len(ann["outside_envelope"]) == 3 and "below" in ann["outside_envelope"][0]


def test_the_envelope_names_every_way_out():
    from homogenization.element_test import programme as programmes
    from homogenization.ann.envelope import outside

    envelope = {"pressures": [2e5, 1e6], "eps_max": 0.1, "kinds": ["constant-volume", "drained"],
                "mesostructure": "h-cell alpha0=55 deg", "cell_parameters": {"alpha0_deg": 55.0}}
    inside = programmes.biaxial(5e5, 0.1, 1e-3, drained=True)
    assert outside(envelope, inside, mesostructure="h-cell alpha0=55 deg", cell_parameters={"alpha0_deg": 55.0}) == []
    assert outside(envelope, programmes.biaxial(2e6, 0.05, 1e-3)) == [
        "p0 = 2e+06 N/m above the highest certified pressure 1e+06 N/m"]
    ratio = (programmes.isotropic(2e5), programmes.proportional_strain(0.01, 0.0, 10))
    assert outside(envelope, ratio) == ["test kind other not certified (certified: constant-volume, drained)"]
    reversal = (programmes.isotropic(2e5), programmes.constant_volume_biaxial(0.08, 80),
                programmes.constant_volume_biaxial(-0.16, 160))
    assert outside(envelope, reversal) == []  # +8 %, then back to -8 %: within +-10 % of the shear start
    assert outside(envelope, inside, mesostructure="h-cell alpha0=40 deg", cell_parameters={"alpha0_deg": 40.0}) == [
        "cell 'h-cell alpha0=40 deg': alpha0_deg = 40 (certified: 55)"]
    assert outside(envelope, inside, mesostructure="hcell:alpha0=55", cell_parameters={"alpha0_deg": 55.0}) == []
    no_p0 = (programmes.constant_volume_biaxial(0.01, 10),)
    assert "before any isotropic compression" in outside(envelope, no_p0)[0]
    tested = {**envelope, "tests": [["constant-volume", "compression", 2e5], ["constant-volume", "compression", 1e6],
                                    ["constant-volume", "reversal", 2e5], ["drained", "compression", 2e5],
                                    ["drained", "compression", 1e6]]}
    assert outside(tested, reversal) == []  # a reversal at the certified 2e5
    assert outside(tested, (programmes.isotropic(5e5), *reversal[1:])) == [
        "a constant-volume reversal stage at p0 = 500000 N/m (certified at 200000 N/m)"]
    assert outside(tested, programmes.biaxial(5e5, 0.05, 1e-3)) == []
    extension = (programmes.isotropic(5e5), programmes.constant_volume_biaxial(-0.05, 50))
    assert outside(tested, extension) == []  # the compression turned by 90 deg
    drained = programmes.biaxial(5e5, 0.05, 1e-3, drained=True)
    cyclic = (*drained, dataclasses.replace(drained[1], target=(-0.08, 5e5), n_increments=80, label="back"))
    assert outside(tested, cyclic) == ["a drained reversal stage, which no certified test ran"]
    fine = {**envelope, "increment": 1e-4}
    assert outside(fine, programmes.biaxial(5e5, 0.05, 1e-4)) == []
    assert outside(fine, programmes.biaxial(5e5, 0.05, 1e-3, drained=True)) == [
        "axial strain increment 0.001 coarser than the certified 0.0001"]
    assert outside(fine, reversal) == ["axial strain increment 0.001 coarser than the certified 0.0001"]


def test_uncertified_failed_and_mismatched_models_are_refused_unless_asked(tmp_path, short_certificate, capsys):
    model = _copy_shipped(tmp_path / "m")
    meta = json.loads(model.with_suffix(".json").read_text())
    meta.pop("certificate", None)
    model.with_suffix(".json").write_text(json.dumps(meta))
    out = tmp_path / "run"
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(out)]) == 2
    assert "the model is uncertified" in _one_error(capsys) and not out.exists()

    _write(model, dataclasses.replace(short_certificate, passed=False, worst=0.05, worst_test="x"))
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(out)]) == 2
    assert "failed its certificate (worst 5 %" in _one_error(capsys) and not out.exists()

    _write(model, short_certificate)
    _perturb(model, 1e-9)  # another file, the same behaviour to the eye
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(out)]) == 2
    line = _one_error(capsys)
    assert "measured on another model file" in line and "--uncertified-ok" in line and not out.exists()

    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--uncertified-ok", "--out", str(out)]) == 0
    assert "UNCERTIFIED (its certificate was measured on another model file" in capsys.readouterr().out
    with h5py.File(out / "run.h5") as f:
        ann = json.loads(f.attrs["parameters"])["ann_model"]
    assert not ann["certified"] and "another model file" in ann["certificate_problem"]


def test_a_weakened_certificate_of_a_perturbed_model_is_not_passed_and_the_backend_refuses_it(tmp_path, capsys):
    """The user's case: the shipped weights with the mean free-DOF rate shifted by four standard
    deviations, certified on 2 orientations to 0.05 % strain without rollouts, came out "PASSED"
    (worst 0.65 %) and ran; now the certificate is weak (exit 4) and biaxial refuses the model."""
    model = _copy_shipped(tmp_path / "w")
    _perturb(model, 4.0)
    argv = ["--model", str(model), "--orientations", "2", "--eps-max", "0.0005", "--no-rollout", "--write"]
    assert run_main(certify.main, argv) == certificate.EXIT_WEAK
    printed = capsys.readouterr().out
    stored = json.loads(model.with_suffix(".json").read_text())["certificate"]
    assert stored["model_sha256"] == file_sha256(model) and len(stored["tests"]) == 3 * len(certificate.PRESSURES) + 1
    assert stored["within_target"] and not stored["passed"] and stored["verdict"] == "weak"
    assert "NOT PASSED (weak)" in printed and "2 orientations (minimum 24)" in printed
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(tmp_path / "run")]) == 2
    line = _one_error(capsys)
    assert "below the minimum certificate (eps_max 0.0005 (minimum 0.1); 2 orientations" in line
    assert not (tmp_path / "run").exists()
    stored["passed"] = True  # a flag edited by hand changes nothing: the settings are read
    model.with_suffix(".json").write_text(json.dumps({**json.loads(model.with_suffix(".json").read_text()),
                                                      "certificate": stored}))
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(tmp_path / "run")]) == 2
    assert "below the minimum certificate" in _one_error(capsys)


def test_certify_refuses_bad_input_before_any_test(tmp_path, capsys):
    model = _copy_shipped(tmp_path / "b")
    fast = ["--model", str(model), "--orientations", "2", "--eps-max", "0.0005", "--no-rollout"]
    (tmp_path / "kept.json").write_text("keep")
    (tmp_path / "file").write_text("")
    cases = {("--out", str(tmp_path / "kept.json")): "exists; pass --overwrite",
             ("--out", str(tmp_path)): "is a folder",
             ("--out", str(tmp_path / "file" / "c.json")): "is not a folder",
             ("--data", str(tmp_path / "none.h5")): "no such database file",
             ("--data", str(tmp_path / "file")): "not a",
             ("--model", str(tmp_path / "none.pt")): "no such model file"}
    for extra, message in cases.items():
        argv = [*fast, *extra] if extra[0] != "--model" else [*extra, *fast[2:]]
        assert run_main(certify.main, argv) == 2, extra
        assert message in _one_error(capsys), extra
    assert (tmp_path / "kept.json").read_text() == "keep"
    assert "exit codes: 0" in certify.build_parser().format_help()


def test_certify_refuses_the_database_of_another_cell_and_keeps_the_index(tmp_path, capsys):
    """--data of another mesostructure rebuilt the model's out-of-distribution index from the wrong cell (its coverage
    fell from 34 % to 0) or raised a traceback (a 3D database)."""
    from dem_database import build  # noqa: PLC0415
    from warp_hcell.mesostructures.hcell import h_cell  # noqa: PLC0415

    model = _copy_shipped(tmp_path / "m")
    index = (model.parent / "m_ood.npz").read_bytes()
    db = build(tmp_path / "db40.h5", mesostructure=h_cell(40.0), precompression=(0.0, 2e-3), n_directions=4,
               spacing=1e-2, leg_length=0.02, threads=1)
    argv = ["--model", str(model), "--data", str(db), "--orientations", "2", "--eps-max", "0.0005", "--no-rollout"]
    assert run_main(certify.main, argv) == 2
    error = _one_error(capsys)
    assert "is a database of mesostructure" in error and error.endswith("give the model's own database")
    assert (model.parent / "m_ood.npz").read_bytes() == index


def test_certify_of_a_failing_model_exits_3(tmp_path, capsys):
    model = _copy_shipped(tmp_path / "f")
    _perturb(model, 2.0)
    argv = ["--model", str(model), "--orientations", "6", "--eps-max", "0.02", "--no-rollout", "--out",
            str(tmp_path / "c.json")]
    assert run_main(certify.main, argv) == certificate.EXIT_FAILED
    assert "FAILED: worst" in capsys.readouterr().out
    cert = json.loads((tmp_path / "c.json").read_text())
    assert cert["verdict"] == "failed" and not cert["passed"] and cert["worst"] > certificate.TARGET


def test_hmodel_train_certifies_and_a_model_of_a_tiny_database_fails_and_is_refused(tmp_path, capsys, monkeypatch):
    """A few epochs on a small database (the issue's model known to fail): `hmodel train --no-enrich`
    writes it with its failed certificate; the backend refuses it in one line. Interrupted during its certificate,
    the same command certifies the model it trained (it was refused: the model existed)."""
    from dem_database import build
    from homogenization.cli import hmodel
    from warp_hcell.mesostructures.hcell import h_cell

    db = build(tmp_path / "db.h5", mesostructure=h_cell(55.0), precompression=(0.0, 2e-3), n_directions=6,
               spacing=1e-2, leg_length=0.04, threads=1)
    model = tmp_path / "m.pt"
    argv = ["train", "--data", str(db), "--out", str(model), "--epochs", "2", "--hidden", "8", "--threads", "1",
            "--no-rollout", "--no-enrich"]
    certify = certificate.certify

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(certificate, "certify", interrupted)
    assert run_main(hmodel.main, argv) == 130
    trained = model.read_bytes()
    monkeypatch.setattr(certificate, "certify", certify)
    capsys.readouterr()
    assert hmodel.main(argv) == certificate.EXIT_FAILED
    printed = capsys.readouterr().out
    assert "trained before with these options, not yet certified" in printed and model.read_bytes() == trained
    meta = json.loads(model.with_suffix(".json").read_text())
    cert = meta["certificate"]
    assert "active round" not in printed and "active_learning" not in meta  # --no-enrich: certify only
    assert "FAILED" in printed and not cert["passed"] and cert["worst"] > certificate.TARGET
    assert cert["model_sha256"] == file_sha256(model) and len(cert["tests"]) == 3 * len(certificate.PRESSURES) + 1
    assert run_main(biaxial.main, [*RUN, "--model", str(model), "--out", str(tmp_path / "run")]) == 2
    assert "failed its certificate" in _one_error(capsys)


def test_bvp_refuses_a_failed_model_and_its_run_records_the_certificate(tmp_path, short_certificate, capsys):
    from homogenization.cli import bvp

    model = _copy_shipped(tmp_path / "f")
    _write(model, dataclasses.replace(short_certificate, passed=False, worst=0.05, worst_test="x"))
    argv = ["--backend", "ann", "--model", str(model), "--alpha0", "40", "--p0", "5.85e6", "--eps-max", "0.002",
            "--increment", "1e-3", "--orientations", "4", "--elements", "1,1"]
    assert run_main(bvp.main, [*argv, "--out", str(tmp_path / "no")]) == 2
    assert "failed its certificate" in _one_error(capsys) and not (tmp_path / "no").exists()
    assert run_main(bvp.main, [*argv, "--uncertified-ok", "--out", str(tmp_path / "yes")]) == 0
    assert "UNCERTIFIED (the model failed its certificate" in capsys.readouterr().out
    with h5py.File(tmp_path / "yes" / "run.h5") as f:
        stored = json.loads(f.attrs["parameters"])["ann_certificate"]
    assert stored["certified"] is False and stored["worst"] == 0.05


def test_constant_volume_extension_is_compression_turned_for_an_even_orientation_set():
    """Why the certificate runs constant-volume extension only for an odd number of orientations:
    with an even set the turned compression test gives the same p and q (q negated) to round-off."""
    from homogenization.element_test import driver, programme as programmes
    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.hcell import h_cell

    model, meso = make_cell_model("analytical"), h_cell(55.0, 0.5)
    curves = {}
    for n_orientations in (6, 5):
        for sign in (1.0, -1.0):
            record = driver.run(model, (programmes.isotropic(2e5, increment=1e-4),
                                        programmes.constant_volume_biaxial(sign * 0.01, 100)),
                                mesostructure=meso, n_orientations=n_orientations, progress=False)
            curves[n_orientations, sign] = (record.p, record.q)
    np.testing.assert_allclose(curves[6, 1.0][0], curves[6, -1.0][0], rtol=1e-12)
    np.testing.assert_allclose(curves[6, 1.0][1], -curves[6, -1.0][1], rtol=1e-12, atol=1e-9)
    assert np.abs(curves[5, 1.0][1] + curves[5, -1.0][1]).max() > 1e-6 * np.abs(curves[5, 1.0][1]).max()
    assert len(certificate.tests_of(n_orientations=5)) == len(certificate.tests_of(n_orientations=6)) + 2
