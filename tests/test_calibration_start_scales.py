"""hmodel calibrate --start-scales: one least-squares fit from the --start-point with one parameter times each
factor, the lowest chi-square kept and every fit recorded; the walkers start where a lone --start-point at the kept
point starts them; bad combinations are one line and exit 2 before any run."""

import json

import numpy as np
import pytest
from cli_checks import TOY_CALIBRATION, assert_one_line_refusal, toy_biaxial_data

from homogenization.calibration import start as start_mod
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

FAST = [*TOY_CALIBRATION, "--steps", "1"]


def _start(tmp_path, name: str, *extra: str) -> dict:
    out = tmp_path / name
    assert run_main(calibrate.main, [*toy_biaxial_data(tmp_path), *FAST, "--out", str(out), *extra]) == 0
    return json.loads((out / "run.json").read_text())["start"]


def test_the_lowest_of_the_scaled_fits_is_kept_and_every_fit_recorded(tmp_path, monkeypatch):
    """Three factors on phi_g: three fits, each from its scaled point (alpha0 as given), the kept one the lowest
    chi-square; its optimum is the one a lone --start-point at that scaled point reaches (1e-9); the scales are in
    the chain's settings. Each fit is cut to 3 residual evaluations, so that they stop apart, as on a rough
    objective."""
    monkeypatch.setattr(start_mod, "MAP_MAX_EVALUATIONS", 3)
    point = "phi_g=20,alpha0=55"
    start = _start(tmp_path, "scaled", "--start-point", point, "--start-scales", "phi_g=0.8,1.25,1.6")
    fits = start["fits"]
    assert start["least_squares_starts"] == 3 and len(fits) == 3
    assert [f["refit_from"]["phi_g"] for f in fits] == pytest.approx([16.0, 25.0, 32.0], rel=1e-12)
    assert all(f["refit_from"]["alpha0"] == pytest.approx(55.0, rel=1e-12) for f in fits)
    chi = [f["chi_square"] for f in fits]
    kept = int(np.argmin(chi))
    assert start["chi_square"] == min(chi) and start["refit_from"] == fits[kept]["refit_from"]
    from homogenization.calibration.report import start_line  # noqa: PLC0415

    assert "the best of 3 fits from scaled start points" in start_line(start)
    assert start["optimum"] == fits[kept]["optimum"]
    assert max(chi) > 1.01 * min(chi)  # the fits stop apart: the choice matters here
    alone = _start(tmp_path, "alone", "--start-point",
                   f"phi_g={fits[kept]['refit_from']['phi_g']!r},alpha0={fits[kept]['refit_from']['alpha0']!r}")
    assert alone["least_squares_starts"] == 1 and "refit_from" not in alone["fits"][0]
    for name, value in alone["optimum"].items():
        assert start["optimum"][name] == pytest.approx(value, rel=1e-9)
    config = json.loads((tmp_path / "scaled" / "run.json").read_text())["config"]
    assert config["start_scales"] == {"phi_g": [0.8, 1.25, 1.6]}


@pytest.mark.parametrize("flags, expected", [
    (["--start-scales", "phi_g=0.5,1"], "no --start-point"),
    (["--start-point", "phi_g=20,alpha0=55", "--start-scales", "kn=0.5,1"], "kn is not in --params"),
    (["--start-point", "phi_g=20,alpha0=55", "--start-scales", "phi_g=0.5,3"], "outside the prior"),
    (["--start-point", "phi_g=60,alpha0=55"], "--start-point phi_g=60 is outside the prior"),  # was clipped silently
    (["--start-point", "phi_g=20,alpha0=55", "--start-scales", "phi_g=0,1"], "factors > 0"),
    (["--start-point", "phi_g=20,alpha0=55", "--start-scales", "phi_g"], "is not NAME=F1,F2"),
])
def test_bad_scales_exit_2_before_any_run(tmp_path, capsys, flags, expected):
    out = tmp_path / "cal"
    assert_one_line_refusal(capsys, calibrate.main, [*toy_biaxial_data(tmp_path), *FAST, *flags, "--out", str(out)],
                            expected, out)


def test_a_chain_whose_every_walker_failed_is_no_posterior(tmp_path, capsys):
    """A drained test at p0 = 3e4 to 2 %: at phi_g = 44.5 deg its forward runs fail (non-finite curves), so every
    walker keeps a log posterior of -inf. The run said "phi_g: constrained" and exited 0; now no posterior."""
    data, out = tmp_path / "drained.csv", tmp_path / "cal"
    data.write_text("# test = drained\n# p0 = 3e4\neps1,q\n0.005,1.5e5\n0.01,2.6e5\n0.015,3.4e5\n0.02,4.1e5\n")
    argv = ["--data", str(data), "--orientations", "12", "--confirm", "none", "--resolution", "off", "--params",
            "phi_g,alpha0", "--walkers", "6", "--steps", "2", "--start-point", "phi_g=44.5,alpha0=50", "-q",
            "--out", str(out)]
    assert run_main(calibrate.main, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error: no posterior" in err[0] and "at every retained step" in err[0], err
    assert not (out / "posterior.json").exists() and not (out / "run.json").exists()


def test_an_overwrite_whose_start_is_refused_keeps_the_finished_run(tmp_path, capsys):
    """--overwrite replaces a finished calibration only once the new one has started: a start refused by the
    resolution check left an empty chain beside the old posterior (the chain deleted first)."""
    out = tmp_path / "cal"
    argv = [*toy_biaxial_data(tmp_path), *TOY_CALIBRATION, "--start-point", "phi_g=25,alpha0=55", "--out", str(out)]
    assert run_main(calibrate.main, [*argv, "--steps", "2"]) == 0
    before = {name: (out / name).read_bytes() for name in ("chain.h5", "posterior.json", "run.json")}
    refused = [a for a in argv if a not in ("--resolution", "off")]
    assert run_main(calibrate.main, [*refused, "--steps", "3", "--resolution", "check", "--overwrite"]) == 2
    assert "--resolution correct" in capsys.readouterr().err
    assert {name: (out / name).read_bytes() for name in before} == before
