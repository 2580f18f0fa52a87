"""A 3D cell's kinematics (hcell3d-axisym) survives its description, its file, the database and the model
file made on it, and the ANN backend runs a cell only with the kinematics its certificate's tests drove, so
that nothing silently falls back to the projected kinematics (docs/triaxial.md, Static liquefaction in 3D)."""

import json
import warnings

import pytest

from homogenization.material.orientation import cell_kinematics
from warp_hcell.mesostructures.files import describe, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import build_h_cell_3d
from warp_hcell.mesostructures.mesostructure import MesostructureError


def test_axisymmetric_kinematics_round_trip_through_the_description():
    cell = build_h_cell_3d(54.0, axisymmetric=True)
    again = from_description(describe(cell))
    assert cell_kinematics(again) == "axisymmetric" and again.parameters == cell.parameters
    plain = build_h_cell_3d(54.0)
    assert "kinematics" not in json.loads(describe(plain))  # other cells keep their description text
    assert cell_kinematics(from_description(describe(plain))) == "projected"


def test_axisymmetric_kinematics_read_from_a_file(tmp_path):
    data = json.loads(describe(build_h_cell_3d(54.0)))
    grains = [{"radius": r, "position": x, "driven": d} for r, x, d in zip(data["radius"], data["position"], data["driven"])]
    text = {"name": "axisym", "cell_size": data["cell_size"], "outer": [[i + 1 for i in f] for f in data["outer"]],
            "grains": grains, "kinematics": "axisymmetric"}
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(text))
    assert cell_kinematics(load_mesostructure(path)) == "axisymmetric"
    text["kinematics"] = "axisymetric"
    path.write_text(json.dumps(text))
    with pytest.raises(MesostructureError, match="kinematics = 'axisymetric' is not one of projected, axisymmetric"):
        load_mesostructure(path)


def test_database_and_model_file_carry_the_kinematics(tmp_path):
    """``generate`` stores the cell's description (and its start cells') in the database, training copies it
    into the model file: both rebuild the axisymmetric cell, not the projected one with the same grains."""
    import h5py

    from training import train
    from training.checkpoint import read_metadata
    from warp_hcell import generate as generate_command

    db, model = tmp_path / "db.h5", tmp_path / "m.pt"
    assert generate_command.main(["--mesostructure", "hcell3d-axisym:alpha0=54", "--samples", "60", "--chunk-size", "30",
                                  "--precompression", "0", "1e-3", "--n-directions", "6", "--sample-spacing", "1e-2",
                                  "--threads", "1", "--out", str(db), "--quiet"]) == 0
    with h5py.File(db, "r") as f:
        cell = from_description(str(f.attrs["mesostructure"]))
        starts = [from_description(text) for text in json.loads(f.attrs["start_mesostructures"])]
    assert cell_kinematics(cell) == "axisymmetric" and [cell_kinematics(s) for s in starts] == ["axisymmetric"]
    with warnings.catch_warnings():  # R^2 of 60 samples in 2 epochs may meet empty slices: not what is tested here
        warnings.simplefilter("ignore", RuntimeWarning)
        assert train.main(["--data", str(db), "--out", str(model), "--epochs", "2", "--hidden", "8", "--no-rollout",
                           "--quiet"]) == 0
    assert cell_kinematics(from_description(read_metadata(model)["mesostructure"])) == "axisymmetric"


def certified_copy(tmp_path, kinematics: str):
    """The shipped 3D model (certified on the projected cell hcell3d:alpha0=55) copied to ``tmp_path`` with its
    certificate's recorded cell parameters declaring ``kinematics`` (the .pt, so its certificate, unchanged)."""
    import shutil

    from homogenization.ann import default_model_path
    from warp_hcell.mesostructures.hcell import AXISYMMETRIC_KINEMATICS

    source = default_model_path(3)
    for path in source.parent.glob(f"{source.stem}*"):
        shutil.copy(path, tmp_path / path.name)
    meta_path = tmp_path / f"{source.stem}.json"
    meta = json.loads(meta_path.read_text())
    cert = meta["certificate"]
    for parameters in (cert["cell_parameters"], cert["envelope"]["cell_parameters"]):
        parameters.pop(AXISYMMETRIC_KINEMATICS, None)
        if kinematics == "axisymmetric":
            parameters[AXISYMMETRIC_KINEMATICS] = 1.0
    meta_path.write_text(json.dumps(meta))
    return tmp_path / source.name


@pytest.mark.parametrize("certified", ["projected", "axisymmetric"])
def test_the_ann_runs_only_the_kinematics_its_certificate_drove(tmp_path, certified):
    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.builders import resolve_mesostructure

    model = certified_copy(tmp_path, certified)
    for spec, kinematics in (("hcell3d:alpha0=55", "projected"), ("hcell3d-axisym:alpha0=55", "axisymmetric")):
        ann = make_cell_model("ann", dim=3, model=model)
        assert ann.certified_kinematics == certified
        ann.init_state(resolve_mesostructure(spec), 1)  # same grains and start state: the model takes both cells
        if kinematics == certified:
            assert ann.certificate_problem is None
        else:
            assert ann.certificate_problem.endswith(f"its certificate drove the cells with the {certified} kinematics, "
                                                    f"{spec!r} declares the {kinematics} kinematics")


def test_triaxial_refuses_an_ann_certified_on_the_other_kinematics(tmp_path, capsys):
    import h5py

    from homogenization import hmodel

    model = certified_copy(tmp_path, "axisymmetric")
    argv = ["triaxial", "--backend", "ann", "--model", str(model), "--p0", "2e5", "--eps-max", "1e-3",
            "--increment", "1e-3", "--order", "3", "--spins", "1"]
    assert hmodel.main([*argv, "--mesostructure", "hcell3d:alpha0=55", "--out", str(tmp_path / "projected")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "certificate drove the cells with the axisymmetric kinematics" in err
    assert not (tmp_path / "projected" / "run.h5").exists()
    assert hmodel.main([*argv, "--mesostructure", "hcell3d-axisym:alpha0=55", "--out", str(tmp_path / "axisym")]) == 0
    assert "certificate passed (worst" in capsys.readouterr().out
    # run anyway: the run file says uncertified, and why, where the model file alone would say certified
    assert hmodel.main([*argv, "--mesostructure", "hcell3d:alpha0=55", "--uncertified-ok",
                        "--out", str(tmp_path / "anyway")]) == 0
    with h5py.File(tmp_path / "anyway" / "run.h5", "r") as f:
        record = json.loads(f.attrs["parameters"])["ann_model"]
    assert record["certified"] is False and "axisymmetric kinematics" in record["certificate_problem"]
