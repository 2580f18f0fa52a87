"""--renewal-phases: which cells the critical-state rule renews together, chosen on hmodel biaxial, triaxial and
calibrate; recorded in run.json and posterior.json, replayed by --posterior; refused in one line without a rule."""

import json
from pathlib import Path

import numpy as np
import pytest

from homogenization.calibration import posterior as post_mod
from homogenization.cli import calibrate, hmodel
from homogenization.cli.options import RENEWAL_PHASES
from homogenization.material.critical_state import PHASES
from homogenization.output import io
from tests.test_density import read_curve
from warp_hcell.core.cli import run_main

BIAXIAL = ["biaxial", "--critical-state", "--drained", "--orientations", "12", "--eps-max", "0.05", "--increment",
           "2e-3", "--p0", "2e5", "-q"]
FAST = ["--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none",
        "--resolution", "off", "-q"]


def _biaxial(out: Path, *flags: str) -> tuple[str, dict[str, np.ndarray]]:
    assert hmodel.main([*BIAXIAL, *flags, "--out", str(out)]) == 0
    rule = io.read_run(out / io.RUN_FILE).attrs["parameters"]["critical_state"]
    return rule["phases"], read_curve(out / io.CURVE_FILE)


def test_the_choices_are_the_rules():
    assert RENEWAL_PHASES == PHASES


def test_the_phases_reach_the_run_and_change_it(tmp_path):
    """Default and 'cell' are one run; 'axis' renews mirror-image planar cells apart, so sigma12 departs from 0."""
    default, plain = _biaxial(tmp_path / "default")
    cell, same = _biaxial(tmp_path / "cell", "--renewal-phases", "cell")
    axis, other = _biaxial(tmp_path / "axis", "--renewal-phases", "axis")
    assert (default, cell, axis) == ("cell", "cell", "axis")
    np.testing.assert_array_equal(plain["q"], same["q"])
    assert np.max(np.abs(plain["sigma12"])) < 1e-6 * np.max(np.abs(plain["q"]))
    assert np.max(np.abs(other["sigma12"])) > 1e-3 * np.max(np.abs(other["q"]))
    assert abs(other["q"][-1] - plain["q"][-1]) > 0.01 * abs(plain["q"][-1])


@pytest.fixture(scope="module")
def phased_posterior(tmp_path_factory):
    """A tiny calibration (4 walkers x 2 steps) of phi_g with the rule's 'axis' phases; its folder."""
    folder = tmp_path_factory.mktemp("phases")
    data = folder / "d.csv"
    data.write_text("# test = drained\n# p0 = 2e5\neps1,q\n0.004,1.2e5\n0.008,1.6e5\n0.012,1.8e5\n")
    out = folder / "cal"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g", "--critical-state", "--renewal-phases",
                                     "axis", "--walkers", "4", "--steps", "2", "--start", "prior", *FAST,
                                     "--out", str(out)]) == 0
    return out


def test_calibrate_records_the_phases_and_the_replay_runs_them(phased_posterior, tmp_path):
    assert json.loads((phased_posterior / "posterior.json").read_text())["critical_state"]["phases"] == "axis"
    assert post_mod.read_posterior(phased_posterior).forward.critical_state.phases == "axis"
    run = tmp_path / "replay"
    assert hmodel.main(["biaxial", "--posterior", str(phased_posterior), "--drained", "--orientations", "4",
                        "--eps-max", "0.008", "--increment", "4e-3", "--p0", "2e5", "-q", "--out", str(run)]) == 0
    assert io.read_run(run / io.RUN_FILE).attrs["parameters"]["critical_state"]["phases"] == "axis"


@pytest.mark.parametrize("argv, expected", [
    (["biaxial", "--renewal-phases", "axis", "--orientations", "4", "--eps-max", "0.008", "-q"],
     "--renewal-phases needs --critical-state"),
    (["triaxial", "--renewal-phases", "mirror", "--eps-max", "0.008", "-q"], "--renewal-phases needs --critical-state"),
    (["biaxial", "--critical-state", "--renewal-phases", "diagonal", "-q"], "invalid choice: 'diagonal'"),
])
def test_phases_without_a_rule_exit_2(tmp_path, capsys, argv, expected):
    out = tmp_path / "x"
    assert run_main(hmodel.main, [*argv, "--out", str(out)]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert expected in lines[-1], lines
    assert not out.exists()


def test_phases_refused_with_a_posteriors_rule_and_without_the_rule_in_calibrate(phased_posterior, tmp_path, capsys):
    out = tmp_path / "x"
    assert hmodel.main(["biaxial", "--posterior", str(phased_posterior), "--renewal-phases", "cell", "--orientations",
                        "4", "--eps-max", "0.008", "-q", "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "the posterior's critical-state rule sets its phases (axis)" in lines[0], lines
    data = tmp_path / "d.csv"
    data.write_text("# test = drained\n# p0 = 2e5\neps1,q\n0.004,1.2e5\n0.008,1.6e5\n")
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g", "--renewal-phases", "axis",
                                     "--walkers", "4", "--steps", "2", *FAST, "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "--renewal-phases needs --critical-state" in lines[0], lines
    assert not out.exists()
