"""Density as the state, through a calibration: e_min and e_max fitted, then hmodel biaxial --posterior
--void-ratio at another density (and its band)."""

from dataclasses import replace

import numpy as np
import pytest

from homogenization.calibration import posterior as post_mod
from homogenization.calibration.data import read_test
from homogenization.calibration.forward import ForwardSettings, simulate, with_density
from homogenization.cli import calibrate, hmodel
from homogenization.material.density import default_map
from homogenization.output import io
from tests.test_density import FAST_2D, read_curve, write_data
from warp_hcell.core.cli import run_main


@pytest.fixture(scope="module")
def map_posterior(tmp_path_factory):
    """A tiny calibration (4 walkers x 3 steps) of e_min and e_max on two undrained tests at two void ratios."""
    folder = tmp_path_factory.mktemp("map")
    paths, eps1 = [], np.array([0.004, 0.008, 0.012])
    settings = ForwardSettings(n_orientations=4, increment=4e-3, iso_increment=2e-3)
    for e in (0.65, 0.9):  # made by the forward model of the calibration at e_min = 0.55, e_max = 0.95
        test = read_test(write_data(folder / "t.csv", str(e), "undrained"))
        q = simulate(replace(test, eps1=eps1), {"e_min": np.array([0.55])}, with_density(settings, [test], 0.55, 0.95)).q[0]
        path = folder / f"u{e}.csv"
        rows = "\n".join(f"{x:g},{v:.9g}" for x, v in zip(eps1, q))
        path.write_text(f"# test = undrained\n# p0 = 2e5\n# void_ratio = {e}\neps1,q\n{rows}\n")
        paths += ["--data", str(path)]
    out = folder / "cal"
    assert run_main(calibrate.main, [*paths, "--params", "e_min,e_max", "--walkers", "4", "--steps", "3",
                                     "--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3",
                                     "--confirm", "none", "-q", "--out", str(out)]) == 0
    return out


def test_a_calibrated_map_runs_at_any_void_ratio_with_its_band(map_posterior, tmp_path):
    post = post_mod.read_posterior(map_posterior)
    assert set(post.calibrated) == {"e_min", "e_max"} and {"e_min", "e_max"} <= set(post.mean)
    out = tmp_path / "run"
    assert hmodel.main(["biaxial", "--posterior", str(map_posterior), "--void-ratio", "0.8", "--posterior-band", "4",
                        "--orientations", "4", "--eps-max", "0.008", "--increment", "4e-3", "--iso-increment", "2e-3",
                        "-q", "--out", str(out)]) == 0
    stored = io.read_run(out / io.RUN_FILE)
    expected = default_map(2, post.mean["e_min"], post.mean["e_max"])
    assert stored.record.density_map == expected and stored.record.e0 == 0.8
    assert stored.attrs["alpha0_deg"] == pytest.approx(expected.alpha0_deg(0.8), abs=1e-9)  # the cell rounds it to 1e-9 deg
    table = [line for line in (out / "posterior_band.csv").read_text().splitlines() if not line.startswith("#")]
    band = dict(zip(table[0].split(","), map(float, table[-1].split(","))))
    # the band's forward model at the posterior mean starts from the same void ratio as the command's run
    assert band["eps1"] == pytest.approx(0.008)
    assert band["q_forward_at_mean"] == pytest.approx(read_curve(out / io.CURVE_FILE)["q"][-1], rel=1e-3)


def test_a_calibrated_map_needs_a_void_ratio_and_its_own_e_range(map_posterior, tmp_path, capsys):
    for flags, expected in ((["--posterior", str(map_posterior)], "give --void-ratio E"),
                            (["--posterior", str(map_posterior), "--void-ratio", "0.8", "--e-min", "0.5"],
                             "conflict with --posterior")):
        assert hmodel.main(["biaxial", *flags, *FAST_2D, "--out", str(tmp_path / "x")]) == 2
        lines = capsys.readouterr().err.splitlines()
        assert len(lines) == 1 and expected in lines[0], lines
    assert not (tmp_path / "x").exists()




def test_a_calibration_without_void_ratios_refuses_one(tmp_path, capsys):
    data = write_data(tmp_path / "plain.csv", None, "undrained")
    data.write_text(data.read_text().replace("0.001,1e4\n0.002,2e4", "0.004,1.1e6\n0.008,1.8e6"))
    out = tmp_path / "cal"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g", "--walkers", "4", "--steps", "2",
                                     "--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3",
                                     "--confirm", "none", "--start", "prior", "-q", "--out", str(out)]) == 0
    assert "e_min" not in post_mod.read_posterior(out).mean
    capsys.readouterr()
    assert hmodel.main(["biaxial", "--posterior", str(out), "--void-ratio", "0.8", *FAST_2D,
                        "--out", str(tmp_path / "x")]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "its data gave no void ratios" in lines[0] and not (tmp_path / "x").exists()
