"""hmodel calibrate with the Hertz-Mindlin contact law: the forward model of G and nu, a tiny
calibration on synthetic triaxial data made by the Hertz closed form, the law kept in
posterior.json and run by ``hmodel triaxial --posterior``, and 2D data refused."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from homogenization import hmodel
from homogenization.backends.analytical import Analytical3DCell
from homogenization.calibration import bayes, resolution
from homogenization.calibration import posterior as post_mod
from homogenization.calibration.data import Measurement, read_test
from homogenization.calibration.forward import ForwardSettings, simulate
from homogenization.cli import calibrate
from homogenization.element_test import driver, programme as programmes
from homogenization.output import io
from warp_hcell.core.cli import run_main
from warp_hcell.core.parameters import HertzMindlinLaw
from warp_hcell.mesostructures.hcell import build_h_cell_3d

TRUTH = {"phi_g": np.array([24.0]), "shear_modulus": np.array([2e9]), "poisson": np.array([0.2]),
         "alpha0": np.array([60.0])}
INC, ISO, P0 = 2e-3, 1e-3, 1e5
RULE = ForwardSettings(law=HertzMindlinLaw.name, increment=INC, iso_increment=ISO)
"""The rule and increments the CLI runs below use (11 x 4 aligned spins, calibrate's default)."""
EPS1 = np.linspace(0.004, 0.02, 5)


def test_hertz_forward_matches_the_driver_on_one_hertz_cell_model(tmp_path):
    """The batched population of Hertz cells (with_hertz_cell_laws) against driver.run of one
    Analytical3DCell built on HertzMindlinLaw, drained triaxial at p0 = 1e5 Pa."""
    sets = {"phi_g": np.array([24.0, 30.0]), "shear_modulus": np.array([2e9, 3e10]),
            "poisson": np.array([0.2, 0.3]), "alpha0": np.array([60.0, 60.0])}
    settings = replace(RULE, lebedev_order=5, n_spins=2)
    batch = simulate(Measurement("t", tmp_path / "t.csv", True, P0, EPS1, {}, 3), sets, settings)
    n_shear = round(EPS1[-1] / INC)
    programme = programmes.triaxial(P0, n_shear * INC, INC, test="drained", iso_increment=ISO)
    for i in range(2):
        law = HertzMindlinLaw(sets["shear_modulus"][i], sets["poisson"][i], sets["phi_g"][i])
        record = driver.run(Analytical3DCell(law, 0.5), programme, mesostructure=build_h_cell_3d(sets["alpha0"][i], radius=0.5),
                            lebedev_order=5, n_spins=2, staggered_spins=False, progress=False)
        start = np.flatnonzero(record.stage == "shear")[0] - 1
        e1 = record.eps11[start:] - record.eps11[start]
        np.testing.assert_allclose(batch.q[i], np.interp(EPS1, e1, record.q[start:]), rtol=0, atol=2e-4 * P0)
    assert batch.q[1, -1] != pytest.approx(batch.q[0, -1], rel=0.05)  # the two laws give other curves
    assert not batch.n_fallback.any()


@pytest.fixture(scope="module")
def hertz_data(tmp_path_factory) -> Path:
    """Drained triaxial q and eps_v of the Hertz closed form at ``TRUTH``, 1 % seeded noise on q."""
    folder = tmp_path_factory.mktemp("hertz")
    clean = simulate(Measurement("t", folder / "t.csv", True, P0, EPS1, {}, 3), TRUTH, RULE)
    q = clean.q[0] * (1.0 + 0.01 * np.random.default_rng(3).standard_normal(EPS1.size))
    rows = "\n".join(f"{e:.6g},{a:.9g},{b:.9g}" for e, a, b in zip(EPS1, q, clean.eps_v[0]))
    path = folder / "tri.csv"
    path.write_text(f"# test = triaxial_drained\n# p0 = {P0:g}\neps1,q,eps_v\n{rows}\n")
    return path


@pytest.fixture(scope="module")
def hertz_posterior(hertz_data, tmp_path_factory) -> Path:
    """The data's own forward model, so without the resolution check (most of the run's time); that the
    check's finer models keep the law is test_the_resolution_checks_finer_models_keep_the_hertz_law."""
    out = tmp_path_factory.mktemp("hertzcal") / "cal"
    assert run_main(calibrate.main, [
        "--data", str(hertz_data), "--law", "hertz-mindlin", "--params", "shear_modulus,phi_g", "--walkers", "4",
        "--steps", "4", "--poisson", "0.2", "--alpha0", "60", "--noise", "0.01", "--increment", str(INC),
        "--iso-increment", str(ISO), "--resolution", "off", "--confirm", "none", "--seed", "3", "-q",
        "--out", str(out)]) == 0
    return out


def test_the_resolution_checks_finer_models_keep_the_hertz_law():
    for knob in ("increment", "orientations"):
        finer = resolution.refined(RULE, knob)
        assert finer.law == HertzMindlinLaw.name and finer != RULE


def test_hertz_likelihood_peaks_at_the_truth_and_the_calibration_finds_it(hertz_data, hertz_posterior):
    """Along log10 G (the others at the truth) the log posterior is largest at the grid value of the
    truth; the CLI's posterior (map start) has G and phi_g within a few per cent of the truth."""
    test = read_test(hertz_data)
    fixed = {k: float(v[0]) for k, v in TRUTH.items()}
    prior = bayes.make_prior(("shear_modulus",), dim=3, law=HertzMindlinLaw.name)
    log_post = bayes.Posterior([test], prior, replace(RULE, fixed=fixed), 0.01)
    grid = np.log10(2e9) + np.arange(-0.5, 0.55, 0.1)
    assert np.argmax(log_post(grid[:, None])) == 5
    posterior = json.loads((hertz_posterior / "posterior.json").read_text())
    assert abs(posterior["shear_modulus"]["mean"] / 2e9 - 1.0) <= 0.1
    assert abs(posterior["phi_g"]["mean"] - 24.0) <= 1.0
    run = json.loads((hertz_posterior / "run.json").read_text())
    assert run["config"]["forward"]["law"] == "hertz-mindlin" and set(run["config"]["forward"]["fixed"]) == set(TRUTH)
    assert run["config"]["prior"]["shear_modulus"] == {"low": 1e6, "high": 1e11, "log": True}


def test_hertz_posterior_round_trip_and_triaxial_runs_it(hertz_posterior, tmp_path):
    stored = json.loads((hertz_posterior / "posterior.json").read_text())
    mean = {k: v["mean"] for k, v in stored.items() if k != "contact_law"}
    assert stored["contact_law"] == {"law": "hertz-mindlin", "shear_modulus": mean["shear_modulus"],
                                     "poisson": 0.2, "phi_g_deg": mean["phi_g"]}
    post = post_mod.read_posterior(hertz_posterior)
    assert post.forward.law == "hertz-mindlin"
    assert post.contact_law == HertzMindlinLaw(mean["shear_modulus"], 0.2, mean["phi_g"])
    out = tmp_path / "pred"
    assert hmodel.main(["triaxial", "--posterior", str(hertz_posterior), "--posterior-band", "4", "--drained",
                        "--p0", f"{P0:g}", "--eps-max", "0.02", "--increment", str(INC), "--iso-increment", str(ISO),
                        "--order", "11", "--spins", "4", "--aligned-spins", "-q", "--out", str(out)]) == 0
    params = io.read_run(out / io.RUN_FILE).attrs["parameters"]
    assert params["contact_law"]["law"] == "hertz-mindlin"
    assert params["contact_law"]["shear_modulus"] == mean["shear_modulus"]
    assert params["posterior"]["contact_law"] == stored["contact_law"]


def test_a_linear_posterior_without_a_law_key_reads_as_linear(tmp_path):
    """posterior.json of the linear law names no law (as before the law was a setting)."""
    folder = tmp_path / "cal"
    folder.mkdir()
    (folder / "posterior.json").write_text(json.dumps({"phi_g": {"mean": 25.0, "median": 25.0, "ci95": [24, 26]}}))
    forward = {"radius": 0.5, "increment": INC, "fixed": {"phi_g": 30.0, "kn": 3e8, "kt_over_kn": 0.6, "alpha0": 60.0}}
    (folder / "run.json").write_text(json.dumps({"config": {"forward": forward}, "data_dimensions": [3]}))
    post = post_mod.read_posterior(folder)
    assert post.forward.law == "linear" and post.contact_law.kn == 3e8 and post.contact_law.phi_g_deg == 25.0


@pytest.mark.parametrize("argv, expected", [
    (["--params", "shear_modulus"], "is defined for spheres"),
    (["--params", "kn", "--data-3d"], "not a parameter of the hertz-mindlin contact law"),
])
def test_hertz_refusals_exit_2(argv, expected, hertz_data, tmp_path, capsys):
    flat = tmp_path / "u.csv"
    flat.write_text("# test = undrained\n# p0 = 3e6\neps1,q\n0.004,1.1e6\n0.008,1.8e6\n")
    data = hertz_data if "--data-3d" in argv else flat
    argv = [a for a in argv if a != "--data-3d"]
    out = tmp_path / "out"
    code = hmodel.main(["calibrate", "--data", str(data), "--law", "hertz-mindlin", *argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and expected in err
    assert not out.exists()
