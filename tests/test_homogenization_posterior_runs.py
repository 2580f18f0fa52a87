"""hmodel triaxial / biaxial --posterior: the run at a calibration's posterior mean, what run.h5 records
of it, the --posterior-band CSV and the one-line refusals before any work."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from homogenization.output import io
from homogenization.calibration import posterior as post_mod
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import ForwardSettings, simulate
from homogenization.cli import calibrate, hmodel
from warp_hcell.core.cli import run_main
from warp_hcell.core.provenance import file_sha256

TRUTH = {"phi_g": np.array([24.0]), "kn": np.array([3e8]), "kt_over_kn": np.array([0.6]), "alpha0": np.array([60.0])}
INC, ISO = 2e-3, 1e-3
RUN_3D = ["--drained", "--p0", "2e5", "--eps-max", "0.02", "--increment", str(INC), "--iso-increment", str(ISO),
          "--order", "11", "--spins", "4", "--aligned-spins", "-q"]
"""A drained triaxial test on the calibration's own rule and increments (ForwardSettings 11 x 4, aligned)."""


@pytest.fixture(scope="module")
def posterior_3d(tmp_path_factory) -> Path:
    """A tiny calibration (4 walkers x 4 steps) of phi_g and kt/kn on synthetic drained triaxial data, without the
    resolution correction (the band then runs the plain forward model, which the test replays)."""
    folder = tmp_path_factory.mktemp("post3d")
    eps1 = np.linspace(0.004, 0.02, 5)
    clean = simulate(Measurement("t", folder / "t.csv", True, 2e5, eps1, {}, 3), TRUTH,
                     ForwardSettings(increment=INC, iso_increment=ISO))
    rows = "\n".join(f"{e:.6g},{a:.9g},{b:.9g}" for e, a, b in zip(eps1, clean.q[0], clean.eps_v[0]))
    data = folder / "tri.csv"
    data.write_text(f"# test = triaxial_drained\n# p0 = 2e5\neps1,q,eps_v\n{rows}\n")
    out = folder / "cal"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g,kt_over_kn", "--walkers", "4",
                                     "--steps", "4", "--kn", "3e8", "--alpha0", "60", "--increment", str(INC),
                                     "--iso-increment", str(ISO), "--resolution", "off", "--confirm", "none", "-q",
                                     "--start", "prior", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def posterior_2d(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("post2d")
    data = folder / "u.csv"
    data.write_text("# test = undrained\n# p0 = 3e6\neps1,q\n0.004,1.1e6\n0.008,1.8e6\n0.012,2.2e6\n")
    out = folder / "cal"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g,alpha0", "--walkers", "4", "--steps",
                                     "3", "--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3",
                                     "--confirm", "none", "-q", "--start", "prior", "--out", str(out)]) == 0
    return out


def read_band(path: Path) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    lines = path.read_text().splitlines()
    header = dict(line[2:].split(" = ", 1) for line in lines if line.startswith("# "))
    table = [line for line in lines if not line.startswith("#")]
    names = table[0].split(",")
    values = np.array([[float(v) for v in line.split(",")] for line in table[1:]])
    return header, {name: values[:, i] for i, name in enumerate(names)}


def test_triaxial_runs_at_the_posterior_mean_and_writes_its_band(posterior_3d, tmp_path):
    out = tmp_path / "pred"
    assert hmodel.main(["triaxial", "--posterior", str(posterior_3d / "posterior.json"), "--posterior-band", "6",
                        *RUN_3D, "--out", str(out)]) == 0
    mean = {k: v["mean"] for k, v in json.loads((posterior_3d / "posterior.json").read_text()).items()}
    stored = io.read_run(out / io.RUN_FILE).attrs["parameters"]
    record = stored["posterior"]
    assert record["sha256"] == file_sha256(posterior_3d / "posterior.json")
    assert record["calibrated"] == ["phi_g", "kt_over_kn"] and record["band"]["draws"] == 6
    # the calibrated parameters at their mean, the others at the calibration's fixed values
    assert record["values"] == {**mean, "kn": 3e8, "alpha0": 60.0}
    law = stored["contact_law"]
    assert law["phi_g_deg"] == mean["phi_g"] and law["kt_over_kn"] == pytest.approx(mean["kt_over_kn"], rel=1e-12)
    assert law["kn"] == 3e8 and stored["alpha0_deg"] == 60.0 and stored["radius"] == 0.5
    header, band = read_band(out / "posterior_band.csv")
    assert header["draws"] == "6" and header["failed_draws"] == "0"
    assert np.all(band["q_lo"] <= band["q_median"]) and np.all(band["q_median"] <= band["q_hi"])
    # the band is the quantiles of the forward model over the seeded draws from posterior.h5
    post = post_mod.read_posterior(posterior_3d)
    draws = post_mod.draw_samples(post, 6, seed=0)
    assert set(np.round(draws["phi_g"], 12)) <= set(np.round(_samples(posterior_3d)["phi_g"], 12))
    curves = simulate(Measurement("b", out, True, 2e5, band["eps1"], {}, 3), draws, post.forward)
    np.testing.assert_allclose(band["eps_v_hi"], np.quantile(curves.eps_v, 0.975, axis=0), rtol=1e-9, atol=1e-12)
    # the command's own run on the same rule and increments is the forward model at the mean
    rows = [line.split(",") for line in (out / io.CURVE_FILE).read_text().splitlines()[1:]]
    shear = np.array([[float(v) for v in r[1:]] for r in rows if r[0] == "shear"])
    start = np.array([float(v) for v in [r for r in rows if r[0] == "iso"][-1][1:]])
    e1, q = shear[:, 0] - start[0], shear[:, 7]
    np.testing.assert_allclose(np.interp(band["eps1"], e1, q), band["q_forward_at_mean"], rtol=0, atol=2e-4 * 2e5)
    assert (out / "triaxial.png").read_bytes()[:4] == b"\x89PNG"


def _samples(folder: Path) -> dict[str, np.ndarray]:
    import h5py

    with h5py.File(folder / "posterior.h5", "r") as fh:
        return {k: fh[f"samples/{k}"][()] for k in fh["samples"]}


def test_biaxial_runs_at_the_posterior_mean(posterior_2d, tmp_path):
    out = tmp_path / "pred"
    assert hmodel.main(["biaxial", "--posterior", str(posterior_2d), "--posterior-band", "4", "--p0", "3e6",
                        "--eps-max", "0.012", "--increment", "4e-3", "--orientations", "4", "-q",
                        "--out", str(out)]) == 0
    mean = {k: v["mean"] for k, v in json.loads((posterior_2d / "posterior.json").read_text()).items()}
    stored = io.read_run(out / io.RUN_FILE).attrs["parameters"]
    assert stored["contact_law"]["phi_g_deg"] == mean["phi_g"]
    assert stored["alpha0_deg"] == pytest.approx(mean["alpha0"], rel=1e-9)  # the cell stores 9 decimals
    assert stored["posterior"]["band"]["draws"] == 4
    assert read_band(out / "posterior_band.csv")[1]["p_hi"].size == 3


BAD = {
    "missing file": (["triaxial", "--posterior", "{tmp}/none.json"], "no such file"),
    "2D posterior, triaxial": (["triaxial", "--posterior", "{p2}"], "biaxial (2D) data"),
    "3D posterior, biaxial": (["biaxial", "--posterior", "{p3}"], "triaxial (3D) data"),
    "explicit --kn": (["triaxial", "--posterior", "{p3}", "--kn", "1e8"], "--kn conflict with --posterior"),
    "explicit --alpha0": (["triaxial", "--posterior", "{p3}", "--alpha0", "55"], "--alpha0 conflict"),
    "band without posterior": (["triaxial", "--posterior-band", "3"], "needs --posterior"),
    "band of another test": (["triaxial", "--posterior", "{p3}", "--posterior-band", "3", "--extension"],
                             "drained or undrained test only"),
    "band larger than the samples": (["triaxial", "--posterior", "{p3}", "--posterior-band", "1000"], "holds 8 samples"),
    "ann backend": (["triaxial", "--posterior", "{p3}", "--backend", "ann", "--model", "x.pt"], "--backend ann"),
    "unknown parameter": (["triaxial", "--posterior", "{tmp}/odd/posterior.json"], "'mu' is not a parameter"),
    "no run.json": (["triaxial", "--posterior", "{tmp}/alone/posterior.json"], "no run.json beside it"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_posterior_input_is_one_line_and_exit_2(case, posterior_2d, posterior_3d, tmp_path, capsys):
    argv, expected = BAD[case]
    (tmp_path / "odd").mkdir()
    shutil.copy(posterior_3d / "run.json", tmp_path / "odd")
    (tmp_path / "odd" / "posterior.json").write_text(json.dumps({"mu": {"mean": 0.5}}))
    (tmp_path / "alone").mkdir()
    shutil.copy(posterior_3d / "posterior.json", tmp_path / "alone")
    argv = [a.format(tmp=tmp_path, p2=posterior_2d, p3=posterior_3d) for a in argv]
    code = hmodel.main([*argv, *(["-q"]), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and expected in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
