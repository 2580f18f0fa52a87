"""The shipped Dobrany sand curves read as calibration data and keep the source's figures.

The reference figures (peak q / sigma3' about 5.8 / 4.7 / 3.5 at eps_a 2.7 / 3.5 / 6.3 %, the
specimens dilating by 3-7 %, void ratios 0.524 / 0.545 / 0.588) were read off the source
workbook independently of the conversion script.
"""

from pathlib import Path

import numpy as np
import pytest

from homogenization.calibration.data import read_test

LAB = Path(__file__).resolve().parents[1] / "benchmarks" / "lab_data" / "dobrany_sand"


@pytest.mark.parametrize("name, p0, peak_ratio, eps_at_peak, final_dilation", [
    ("cid_50kpa.csv", 5e4, 5.8, 0.027, 0.073),
    ("cid_100kpa.csv", 1e5, 4.7, 0.035, 0.065),
    ("cid_200kpa.csv", 2e5, 3.5, 0.063, 0.031),
])
def test_triaxial_curves_keep_the_source_figures(name, p0, peak_ratio, eps_at_peak, final_dilation):
    test = read_test(LAB / name)
    assert test.kind == "triaxial_drained" and test.dim == 3 and test.p0 == p0
    q, eps_v = test.observed["q"], test.observed["eps_v"]
    peak = int(np.argmax(q))
    assert q[peak] / p0 == pytest.approx(peak_ratio, abs=0.05)
    assert test.eps1[peak] == pytest.approx(eps_at_peak, abs=0.001)
    assert -eps_v[-1] == pytest.approx(final_dilation, abs=0.001)  # dilation: eps_v < 0 (contraction positive)
    assert 0.2 < test.eps1[-1] < 0.26


def test_licence_and_source_ship_with_the_data():
    notice = (LAB / "LICENSE-source.txt").read_text()
    assert "MIT License" in notice and "Filippo Masi" in notice
    readme = (LAB / "README.md").read_text()
    assert "ALERT-OlekZienkiewicz-ML" in readme and "LICENSE-source.txt" in readme
