"""The contact-law declarations: one registry, one file form, and the runtimes that refuse a law.

- ``to_dict`` / ``contact_law_from_dict`` round-trip every law; the linear law's dict is the
  dataclass's fields alone (files of the linear law are unchanged).
- Unknown laws, unknown keys and values outside a law's ranges are one-line errors.
- The Hertz-Mindlin law is refused by planar cells (both backends), the meso-ANN and the learning
  database, and by the commands with one line and exit code 2 before any output is written.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.cli import hmodel
from warp_hcell.core.parameters import (
    CONTACT_LAWS,
    ContactLaw,
    DatabaseSettings,
    HertzMindlinLaw,
    contact_law_from_dict,
)
from warp_hcell.mesostructures.builders import resolve_mesostructure

DOBRANY_50 = Path(__file__).resolve().parents[1] / "benchmarks" / "lab_data" / "dobrany_sand" / "cid_50kpa.csv"


@pytest.mark.parametrize("law", [ContactLaw(kn=3e7, kt_over_kn=0.8, phi_g_deg=25.0),
                                 HertzMindlinLaw(shear_modulus=1e9, poisson=0.3, phi_g_deg=33.0)])
def test_every_law_round_trips_through_its_file_form(law):
    assert contact_law_from_dict(law.to_dict()) == law == type(law).from_dict(law.to_dict())
    assert CONTACT_LAWS[law.name] is type(law)


def test_a_law_refuses_the_file_form_of_another():
    with pytest.raises(ValueError, match="is not the 'linear' law"):
        ContactLaw.from_dict(HertzMindlinLaw().to_dict())


def test_the_linear_law_is_stored_as_before():
    assert ContactLaw().to_dict() == asdict(ContactLaw())
    assert "law" not in ContactLaw().to_dict()
    assert contact_law_from_dict({"kn": 1e8, "kt_over_kn": 0.5, "phi_g_deg": 30.0}) == ContactLaw(kn=1e8)


def test_hertz_mindlin_moduli_are_those_of_the_grain_material():
    law = HertzMindlinLaw(shear_modulus=29e9, poisson=0.2)
    young = 2.0 * 29e9 * 1.2
    e_star = young / (2.0 * (1.0 - 0.2 ** 2))
    assert math.isclose(law.normal_modulus, 4.0 / 3.0 * e_star, rel_tol=1e-15)
    assert math.isclose(law.shear_stiffness_modulus, 8.0 * 29e9 / (2.0 * (2.0 - 0.2)), rel_tol=1e-15)


@pytest.mark.parametrize("values, message", [
    ({"law": "hertz"}, "unknown contact law 'hertz'"),
    ({"law": "hertz-mindlin", "kn": 1e8}, "has no parameter 'kn'"),
    ({"law": "hertz-mindlin", "poisson": 0.5}, "poisson = 0.5 is outside [0, 0.5)"),
    ({"law": "hertz-mindlin", "shear_modulus": -1.0}, "shear_modulus = -1 must be finite and > 0"),
])
def test_bad_declarations_are_one_line_errors(values, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")) as info:
        contact_law_from_dict(values)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("backend", ["analytical", "dem"])
def test_planar_cells_refuse_the_law_of_spheres(backend):
    with pytest.raises(ValueError, match="defined for spheres"):
        make_cell_model(backend, dim=2, contact_law=HertzMindlinLaw())


def test_the_planar_dem_model_refuses_it_too():
    from warp_hcell.dem.model import DemModel

    with pytest.raises(ValueError, match="defined for spheres"):
        DemModel.build(resolve_mesostructure("hcell"), 1, contact_law=HertzMindlinLaw())


def test_the_meso_ann_and_the_learning_database_refuse_it(tmp_path):
    from homogenization.ann.cell import AnnCell3D
    from warp_hcell.database.generate import generate

    with pytest.raises(ValueError, match="linear contact law only, not 'hertz-mindlin'"):
        AnnCell3D(HertzMindlinLaw(), 0.5)
    out = tmp_path / "db.h5"
    with pytest.raises(ValueError, match="linear contact law only, not 'hertz-mindlin'"):
        generate(resolve_mesostructure("hcell3d"), DatabaseSettings(samples=10, chunk_size=10), out, seed=0,
                          contact_law=HertzMindlinLaw())
    assert not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["biaxial", "--law", "hertz-mindlin"], "the hertz-mindlin contact law is defined for spheres (3D cells, hmodel "
                                            "triaxial); planar cells use the linear law"),
    (["triaxial", "--backend", "ann", "--law", "hertz-mindlin"],
     "the meso-ANN backend (its networks learn from DEM databases of the linear law) supports the linear contact "
     "law only, not 'hertz-mindlin'"),
    (["triaxial", "--law", "hertz-mindlin", "--poisson", "0.7"], "poisson = 0.7 is outside [0, 0.5)"),
    (["calibrate", "--data", str(DOBRANY_50), "--params", "phi_g,kn", "--law", "hertz-mindlin"],
     "--params kn is not a parameter of the hertz-mindlin contact law (--law hertz-mindlin: "
     "phi_g,shear_modulus,poisson,alpha0,alpha0_spread,e_min,e_max,alpha_c,renewal_rate,interlocking_m,e_gamma,"
     "lambda_c,xi_c,cell_spread,mobilisation_strain,mobilisation_start,relax_strain,relax_exponent,softening_strain,"
     "relax_void_slope,mobilisation_exponent,mobilisation_void_slope,map_state_weight)"),
    (["calibrate", "--data", str(DOBRANY_50), "--params", "shear_modulus"],
     "--params shear_modulus is not a parameter of the linear contact law (--law linear: "
     "phi_g,kn,kt_over_kn,alpha0,alpha0_spread,e_min,e_max,alpha_c,renewal_rate,interlocking_m,e_gamma,lambda_c,"
     "xi_c,cell_spread,mobilisation_strain,mobilisation_start,relax_strain,relax_exponent,softening_strain,"
     "relax_void_slope,mobilisation_exponent,mobilisation_void_slope,map_state_weight,stiffness_void_slope,"
     "kn_exponent)"),
])
def test_the_commands_refuse_in_one_line(argv, message, tmp_path, capsys):
    out = tmp_path / "run"
    assert hmodel.main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(message)
    assert not out.exists()


def test_a_hertz_mindlin_triaxial_run_records_its_law(tmp_path):
    import h5py

    out = tmp_path / "run"
    assert hmodel.main(["triaxial", "--law", "hertz-mindlin", "--shear-modulus", "1e9", "--drained", "--p0", "1e5",
                        "--eps-max", "0.004", "--increment", "1e-3", "--order", "3", "--spins", "1", "-q",
                        "--out", str(out)]) == 0
    with h5py.File(out / "run.h5") as f:
        text = " ".join(str(f.attrs[k]) for k in f.attrs)
    assert '"law": "hertz-mindlin"' in text and '"shear_modulus": 1000000000.0' in text
    q = np.loadtxt(out / "curve.csv", delimiter=",", skiprows=1, usecols=8)
    assert np.all(np.isfinite(q)) and q[-1] > 0.0


NUMPY_INTERFACE = ("pair_constants", "normal_force", "normal_stiffness", "shear_stiffness", "move_stiffness",
                   "move_stiffness_slope")
WARP_INTERFACE = ("pair_scale", "pair_constant", "normal_force", "spatial_contact", "kernel_constants",
                  "reference_stiffness")


@pytest.mark.parametrize("name", list(CONTACT_LAWS))
def test_every_registered_law_has_one_module_per_runtime(name):
    from warp_hcell.core.laws import numpy_law
    from warp_hcell.dem.laws import warp_law

    assert numpy_law(name).__name__ == "warp_hcell.core.laws." + name.replace("-", "_")
    assert all(callable(getattr(numpy_law(name), f, None)) for f in NUMPY_INTERFACE)
    assert all(getattr(warp_law(name), f, None) is not None for f in WARP_INTERFACE)
    law = CONTACT_LAWS[name]()
    kn, kt, mu = warp_law(name).kernel_constants(law)
    assert mu == law.mu and kn > 0.0 and kt > 0.0
    radius = np.array([[0.5, 0.25, 0.5]])
    stiffness = np.asarray(warp_law(name).reference_stiffness(law, radius))
    assert np.all(np.isfinite(stiffness)) and np.all(stiffness > 0.0)


def test_a_name_no_law_is_registered_under_is_a_one_line_error():
    from warp_hcell.core.laws import numpy_law
    from warp_hcell.dem.laws import warp_law

    for runtime in (numpy_law, warp_law):
        with pytest.raises(ValueError, match="unknown contact law 'hertz'; choose from linear, hertz-mindlin"):
            runtime("hertz")


def test_the_law_flags_are_built_from_the_declarations():
    import argparse

    from warp_hcell.core.cli import add_contact_law_arguments, contact_law_from_args

    parser = argparse.ArgumentParser()
    add_contact_law_arguments(parser)
    flags = {a for action in parser._actions for a in action.option_strings}
    assert {flag.flag for law in CONTACT_LAWS.values() for flag in law.flags} <= flags
    assert contact_law_from_args(parser.parse_args([])) == ContactLaw()
    assert contact_law_from_args(parser.parse_args(["--kn", "1e8", "--kt", "3e7", "--phi", "25"])) == \
        ContactLaw(kn=1e8, kt_over_kn=3e7 / 1e8, phi_g_deg=25.0)
    assert contact_law_from_args(parser.parse_args(["--law", "hertz-mindlin", "--shear-modulus", "1e9", "--poisson",
                                                    "0.3", "--phi", "25"])) == \
        HertzMindlinLaw(shear_modulus=1e9, poisson=0.3, phi_g_deg=25.0)
    with pytest.raises(ValueError, match="--kn is a flag of the linear law, which --law hertz-mindlin ignores"):
        contact_law_from_args(parser.parse_args(["--law", "hertz-mindlin", "--kn", "5"]))  # it would be ignored
    assert contact_law_from_args(parser.parse_args(["--law", "hertz-mindlin"])) == HertzMindlinLaw()
    with pytest.raises(SystemExit):
        parser.parse_args(["--shear-modulus", "-1"])
