"""A 3D cell's kinematics (hcell3d-axisym) survives its description and its file, so that databases,
model files and certificates made on it do not silently fall back to the projected kinematics."""

import json

import pytest

from homogenization.orientation3d import cell_kinematics
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
