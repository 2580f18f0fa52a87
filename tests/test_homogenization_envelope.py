"""The minimum certificate and the envelope (homogenization.ann.envelope) without running a test."""

import dataclasses
import json

import pytest

from homogenization.ann import envelope
from homogenization.ann.records import Certificate, TestResult
from homogenization.element_test import programme as programmes
from homogenization.ann import default_model_path

SHIPPED = json.loads(default_model_path().with_suffix(".json").read_text())["certificate"] \
    if default_model_path().is_file() else None


def _cert(settings, tests, *, rollout=None, target=0.02, worst=0.0, passed=True):
    """A certificate of these settings, tests and figures (the rest placeholders): a test (kind, sense, p0), or
    (kind, sense) at every pressure of ``settings`` (a reversal at the lowest)."""
    pressures = sorted(settings.get("pressures", [2e5]))
    full = [test for test in tests if len(test) == 3]
    full += [(k, s, p) for k, s in (test for test in tests if len(test) == 2)
             for p in (pressures[:1] if s == "reversal" else pressures)]
    rows = tuple(TestResult(name=f"{k} {s} {p:g}", kind=k, sense=s, p0=p, dp=worst, dq=worst, scale=p, n_increments=1)
                 for k, s, p in full)
    return Certificate(target=target, worst=worst, worst_test="", metric="", tests=rows, rollout=rollout, coverage=None,
                       dem_spread=None, settings=settings, cell_parameters={}, model_sha256="", revision="", seconds=0.0,
                       within_target=worst <= target, below_minimum=[], verdict="", passed=passed)


def test_the_certificate_defaults_are_the_minimum_and_meet_it():
    from homogenization.learning import certificate

    assert (certificate.PRESSURES, certificate.EPS_MAX, certificate.INCREMENT, certificate.TARGET,
            certificate.N_ORIENTATIONS, certificate.SPATIAL_RULE) == (
        envelope.MINIMUM.pressures, envelope.MINIMUM.eps_max, envelope.MINIMUM.increment, envelope.MINIMUM.target,
        envelope.MINIMUM.n_orientations, envelope.MINIMUM.spatial_rule)
    for dim in (2, 3):
        tests = [(info["kind"], info["sense"], info["p0"]) for info, _ in certificate.tests_of(dim=dim)]
        settings = certificate.requested_settings(dim)
        cert = _cert(settings, tests, rollout={"x": 1}, target=certificate.TARGET)
        assert envelope.shortfalls(cert, dim) == []
        weaker = dataclasses.replace(cert, settings={**settings, "pressures": [2e5]}, rollout=None)
        assert envelope.shortfalls(weaker, dim) == ["pressures 200000 (minimum: 200000, 1e+06)",
                                                    "no rollouts (the minimum runs them)"]


def test_a_test_missing_at_one_pressure_is_a_shortfall():
    """Every required test at every minimum pressure the certificate ran (the reversal at any one): a certificate
    whose drained compression ran at 2e5 only is weak; one certified at (1e6, 2e5), its reversal at the first given
    (``certificate.tests_of``), is not."""
    settings = {"pressures": [2e5, 1e6], "eps_max": 0.1, "increment": 1e-4, "n_orientations": 24}
    whole = [(k, s, p) for k, s in envelope.MINIMUM.planar_tests for p in ((2e5,) if s == "reversal" else (2e5, 1e6))]
    assert envelope.shortfalls(_cert(settings, whole, rollout={"x": 1}), 2) == []
    lacking = [t for t in whole if t != ("drained", "compression", 1e6)]
    assert envelope.shortfalls(_cert(settings, lacking, rollout={"x": 1}), 2) == [
        "no drained compression at p0 1e+06 test"]
    from homogenization.learning import certificate

    for pressures in ((1e6, 2e5), (1e5, 2e5, 1e6)):
        ran = [(info["kind"], info["sense"], info["p0"]) for info, _ in certificate.tests_of(pressures=pressures, dim=2)]
        assert envelope.shortfalls(_cert({**settings, "pressures": list(pressures)}, ran, rollout={"x": 1}), 2) == []


def test_a_weak_certificate_within_its_target_is_not_passed_whatever_its_flag():
    cert = _cert({"pressures": [2e5, 1e6], "eps_max": 0.1, "increment": 1e-4, "n_orientations": 2},
                 envelope.MINIMUM.planar_tests, rollout={"x": 1}, target=0.02, worst=0.001, passed=True)
    assert envelope.verdict(cert) == "weak" and envelope.dimension_of(cert) == 2
    assert envelope.shortfalls(cert, 2) == ["2 orientations (minimum 24)"]
    assert envelope.verdict(dataclasses.replace(cert, worst=0.03)) == "failed"
    loose = dataclasses.replace(cert, target=0.5, settings={**cert.settings, "n_orientations": 24})
    assert envelope.verdict(loose) == "weak" and envelope.shortfalls(loose, 2) == ["target 50 % (maximum 2 %)"]
    assert envelope.verdict(dataclasses.replace(cert, settings={**cert.settings, "n_orientations": 24})) == "passed"
    spatial = dataclasses.replace(cert, settings={**cert.settings, "spatial_rule": [5, 2]})
    assert envelope.dimension_of(spatial) == 3
    assert "spatial rule order 5 x 2 spins (minimum 11 x 4)" in envelope.shortfalls(spatial, 3)


def test_step_kinds_of_the_triaxial_programmes():
    iso = programmes.isotropic(2e5, dim=3)
    kinds = {test: [envelope.step_kind(step, 2e5) for step in programmes.triaxial_shear(test, 2e5, 0.1, 100)]
             for test in programmes.TRIAXIAL_TESTS}
    assert kinds == {"undrained": ["undrained"], "drained": ["drained"], "extension": ["drained"],
                     "constant_p": ["other"], "true": ["other"], "cyclic": ["undrained"] * 5}
    assert envelope.step_kind(iso, None) == "other"  # outside() never asks: the isotropic stage sets p0
    env = {"pressures": [2e5, 1e6], "eps_max": 0.1, "kinds": ["drained", "undrained"]}
    cyclic = programmes.triaxial(2e5, 0.1, 1e-3, test="cyclic")
    assert envelope.outside(env, cyclic, unit="Pa") == []
    assert envelope.outside(env, programmes.triaxial(3e6, 0.15, 1e-3, test="constant_p"), unit="Pa") == [
        "p0 = 3e+06 Pa above the highest certified pressure 1e+06 Pa",
        "test kind other not certified (certified: drained, undrained)",
        "axial strain 0.15 beyond the certified 0.1"]


@pytest.mark.skipif(SHIPPED is None, reason="default model not installed")
def test_a_sweep_plans_which_ann_cases_leave_the_envelope_and_warns_once(tmp_path, capsys):
    from homogenization.cli import sweep
    from homogenization.sweeps.plan import plan

    args = sweep.parse_args(["--backend", "ann,analytical", "--p0", "5e4,2e5", "--eps-max", "0.05",
                             "--out", str(tmp_path / "s")])
    cases, _ = plan(args)
    ann = {case.p0: case.parameters["ann_model"]["outside_envelope"] for case in cases if case.backend == "ann"}
    assert ann == {5e4: ["p0 = 50000 N/m below the lowest certified pressure 200000 N/m"], 2e5: []}
    assert sweep.warn_outside_envelope(cases) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["warning: ann: 1 of 2 ann case(s) run outside their model's certificate envelope: p0 = 50000 N/m "
                   "below the lowest certified pressure 200000 N/m (each case's run.h5: ann_model.outside_envelope)"]


@pytest.mark.parametrize("dim", (2, 3))
def test_the_isochoric_step_of_each_dimension_has_its_kind(dim):
    isochoric = {2: programmes.constant_volume_biaxial, 3: programmes.isochoric}[dim]
    drained = {2: programmes.drained_biaxial(2e5, 0.1, 100), 3: programmes.triaxial_shear("drained", 2e5, 0.1, 100)[0]}
    assert envelope.step_kind(isochoric(0.1, 100), 2e5) == {2: "constant-volume", 3: "undrained"}[dim]
    assert envelope.step_kind(isochoric(-0.05, 50), 2e5) == {2: "constant-volume", 3: "undrained"}[dim]
    assert envelope.step_kind(drained[dim], 2e5) == "drained"
