"""Loading programmes: constructors, validation, dict round trip."""

from __future__ import annotations

import json

import pytest

from homogenization.element_test import programme as programmes
from homogenization.element_test.programme import Step
from warp_hcell.core.parameters import LoadingDefaults


def test_constant_volume_and_drained_constructors():
    cv = programmes.constant_volume_biaxial(0.2, 20000)
    assert cv.control == ("strain", "strain") and cv.target == (0.2, -0.2) and cv.n_increments == 20000
    dr = programmes.drained_biaxial(5.85e6, 0.1, 100)
    assert dr.control == ("strain", "stress") and dr.target == (0.1, 5.85e6) and dr.stress_mask == (False, True)


def test_isotropic_is_strain_driven_until_p0():
    iso = programmes.isotropic(2e5)
    assert iso.control == ("strain", "strain") and iso.stop_at_p == 2e5 and iso.label == "iso"
    assert iso.target[0] / iso.n_increments == pytest.approx(LoadingDefaults.iso_increment)
    assert iso.target[0] == iso.target[1] == pytest.approx(programmes.ISO_MAX_STRAIN)


def test_biaxial_programme():
    programme = programmes.biaxial(5.85e6, 0.2, 1e-5)
    assert [s.label for s in programme] == ["iso", "shear"]
    assert programme[1].n_increments == 20000
    drained = programmes.biaxial(5.85e6, 0.2, 1e-3, drained=True)
    assert drained[1].target == (0.2, 5.85e6)


def test_dict_round_trip_through_json():
    programme = programmes.biaxial(2e5, 0.05, 1e-4, drained=True) + (programmes.proportional_strain(0.01, 0.002, 7, label="probe"),)
    data = json.loads(json.dumps(programmes.to_dict(programme)))
    assert programmes.from_dict(data) == programme


@pytest.mark.parametrize("kwargs, message", [
    (dict(control=("strain", "force"), target=(0.1, 0.0), n_increments=1, label="s"),
     "step 's': control must be two of ('strain', 'stress'), got ('strain', 'force')"),
    (dict(control=("strain", "strain"), target=(0.1, float("nan")), n_increments=1, label="s"),
     "step 's': target must be two finite numbers, got (0.1, nan)"),
    (dict(control=("strain", "strain"), target=(0.1, 0.0), n_increments=0, label="s"),
     "step 's': n_increments = 0 must be an integer >= 1"),
    (dict(control=("strain", "strain"), target=(0.1, 0.0), n_increments=1, label="a,b"),
     "step label 'a,b' must be a non-empty identifier (letters, digits, _)"),
    (dict(control=("strain", "strain"), target=(1.5, 0.0), n_increments=1, label="s"),
     "step 's': strain change of component 11 = 1.5 must be in (-1, 1)"),
    (dict(control=("strain", "stress"), target=(0.1, 1e5), n_increments=1, label="s", stop_at_p=1e5),
     "step 's': stop_at_p needs strain control on both components"),
    (dict(control=("strain", "strain"), target=(0.1, 0.1), n_increments=1, label="s", stop_at_p=-1.0),
     "step 's': stop_at_p = -1 must be finite and > 0"),
    (dict(control=("strain", "strain"), target=(-0.1, -0.1), n_increments=1, label="s", stop_at_p=1.0),
     "step 's': stop_at_p needs a contracting strain path (target sum > 0)"),
])
def test_invalid_steps_are_one_line_errors(kwargs, message):
    with pytest.raises(ValueError) as info:
        Step(**kwargs)
    assert str(info.value) == message


def test_programme_validation():
    with pytest.raises(ValueError, match="^a loading programme needs at least one step$"):
        programmes.validate(())
    with pytest.raises(ValueError, match="^programme items must be Step, got dict$"):
        programmes.validate(({"label": "x"},))
    with pytest.raises(ValueError, match="^unknown key 'stages' at the top level; expected one of: steps$"):
        programmes.from_dict({"stages": []})
    with pytest.raises(ValueError, match="^malformed loading programme"):
        programmes.from_dict({})
    with pytest.raises(ValueError, match=r"^p0 = 0 must be finite and > 0$"):
        programmes.biaxial(0.0, 0.2, 1e-5)
    with pytest.raises(ValueError, match=r"^increment = 0 must be finite and > 0$"):
        programmes.n_increments_for(0.2, 0.0)
