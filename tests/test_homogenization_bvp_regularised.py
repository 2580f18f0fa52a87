"""The second-gradient biaxial specimen, checkpoints and resume, the band measurement, and their errors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
from cli_checks import assert_usage_error

from homogenization.backends import make_cell_model
from homogenization.cli import bvp
from homogenization.fe import solver as fe
from homogenization.fe.band import measure_band
from homogenization.fe.checkpoint import Checkpoint
from homogenization.fe.second_gradient import SecondGradientSpecimen, reference_modulus
from homogenization.material import orientation
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.core.cli import run_main
from warp_hcell.mesostructures.hcell import h_cell

P0 = 2e5
ROOT = Path(__file__).resolve().parents[1]
TINY = ["--alpha0", "40", "--p0", "2e5", "--eps-max", "0.01", "--increment", "1e-3", "--orientations", "12",
        "--elements", "4,8", "--iso-steps", "5"]


def cli(argv: list[str]) -> int:
    return run_main(bvp.main, argv)


def programme(n_shear: int = 10) -> list[fe.LoadStep]:
    return fe.isotropic_stage(P0, 5) + fe.shear_stage(P0, n_shear * 1e-3, n_shear)


def material_for(specimen: fe.BiaxialSpecimen, n_orientations: int = 12) -> HomogenisedMaterial:
    return HomogenisedMaterial(make_cell_model("analytical"), orientation.orientations(n_orientations), h_cell(40.0),
                               specimen.n_points)


def test_homogeneous_specimen_the_second_gradient_terms_vanish():
    """Uniform strain: v = grad u, grad v = 0, lambda = 0, so the regularised specimen follows the
    plain one (which follows the material point): measured within 1e-12 p0, checked within 1e-9 p0."""
    plain = fe.BiaxialSpecimen(2, 4)
    regular = SecondGradientSpecimen(2, 4, length=0.2, modulus=4e7)
    a = plain.run(material_for(plain), programme(), scale=P0)
    b = regular.run(material_for(regular), programme(), scale=P0)
    for name in ("sigma11", "sigma22", "eps11", "eps22"):
        deviation = max(abs(getattr(r, name) - getattr(s, name)) for r, s in zip(a, b))
        assert deviation <= (1e-9 * P0 if name.startswith("sigma") else 1e-12), name
    assert (b[-1].sigma11 - b[-1].sigma22) > 2.0 * P0  # really sheared


def _face_average(specimen: fe.BiaxialSpecimen, u: np.ndarray, dofs: np.ndarray) -> float:
    """u_x over one lateral face averaged along its length: the trapezoid rule between nodes (bilinear elements),
    Simpson's per element (8-node elements, their edges quadratic)."""
    y = specimen.basis.doflocs[1][dofs]
    order = np.argsort(y)
    y, v = y[order], u[dofs][order]
    if isinstance(specimen, SecondGradientSpecimen):
        h = y[2::2] - y[:-2:2]
        return float(np.sum(h * (v[:-2:2] + 4.0 * v[1::2] + v[2::2]) / 6.0) / (y[-1] - y[0]))
    return float(np.sum(np.diff(y) * 0.5 * (v[1:] + v[:-1])) / (y[-1] - y[0]))


@pytest.mark.parametrize("second_gradient", [False, True], ids=["plain", "second gradient"])
def test_the_lateral_strain_averages_each_face_over_its_length(second_gradient):
    """A weak zone bends the lateral faces: eps22 is u_x averaged along each face (the trapezoid rule, Simpson's
    on 8-node edges), not the mean over its nodes, which weights the end and the midside nodes wrongly."""
    specimen = SecondGradientSpecimen(4, 8, length=0.05, modulus=4e7) if second_gradient else fe.BiaxialSpecimen(4, 8)
    weak = np.repeat(bvp.weak_elements(specimen), specimen.points_per_element())
    material = HomogenisedMaterial(make_cell_model("analytical"), orientation.orientations(12),
                                   [h_cell(50.0) if w else h_cell(40.0) for w in weak], specimen.n_points)
    result = specimen.run(material, fe.isotropic_stage(P0, 5) + fe.shear_stage(P0, 0.03, 15), scale=P0)[-1]
    u = specimen.displacement_of(specimen.last_unknowns)
    faces = -(_face_average(specimen, u, specimen.right_dofs) - _face_average(specimen, u, specimen.left_dofs))
    assert result.eps22 == pytest.approx(faces / specimen.width, rel=1e-12, abs=0.0)
    nodes = -(u[specimen.right_dofs].mean() - u[specimen.left_dofs].mean()) / specimen.width
    assert abs(nodes - result.eps22) > 1e-6 * abs(result.eps22)  # the faces do bend: the rule matters here


def test_second_gradient_newton_converges_fast_to_the_exact_constraint():
    """Each Newton iteration cuts the residual by >= 1e3 (the augmented-Lagrangian step's rate is
    about E_ref / beta = 1e-4), and the converged v is grad u in each element's mean."""
    specimen = SecondGradientSpecimen(2, 4, length=0.2, modulus=4e7)
    weak = np.zeros(specimen.n_points, bool)
    weak[:4] = True  # one weak element: a non-uniform field where the second gradient works
    material = HomogenisedMaterial(make_cell_model("analytical"), orientation.orientations(12),
                                   [h_cell(50.0) if w else h_cell(40.0) for w in weak], specimen.n_points)
    results = specimen.run(material, programme(), scale=P0)
    r = np.array(results[-1].residuals)
    assert r.size >= 3 and r[-1] <= 1e-8 * P0
    assert np.all(r[1:] / r[:-1] < 1e-3), r
    assert np.ptp(results[-1].strain[:, 1]) > 1e-4  # the field is not uniform
    x = specimen.last_unknowns
    grad_u = specimen.basis.interpolate(specimen.displacement_of(x)).grad  # (2, 2, ne, nq)
    v = specimen.v_basis.interpolate(specimen.gradient_of(x)[0]).value  # v_11, (ne, nq)
    dx = specimen.basis.dx
    mean_mismatch = np.abs(((grad_u[0, 0] - v) * dx).sum(axis=1) / dx.sum(axis=1))
    assert mean_mismatch.max() <= 1e-9 * np.abs(grad_u[0, 0]).max()


def test_reference_modulus_is_the_shear_stiffness_at_p0():
    model = make_cell_model("analytical")
    point = HomogenisedMaterial(model, orientation.orientations(12), h_cell(40.0), 1)
    G = reference_modulus(point, P0)
    # central difference of sigma_12 over gamma_12 at p0, from the same isotropic state
    state = point.init_state()
    state = point.update(state, np.array([[1e-6, 1e-6, 0.0]]), with_tangent=False).state
    for k in range(1, 21):
        a = 0.0
        for _ in range(50):
            u = point.update(state, np.array([[a, a, 0.0]]))
            p = 0.5 * (u.stress[0, 0] + u.stress[0, 1])
            if abs(p - P0 * k / 20) <= 1e-10 * P0:
                break
            a += (P0 * k / 20 - p) / (0.5 * u.tangent[0, :2, :2].sum())
        state = u.state
    h = 1e-7
    s = [point.update(state, np.array([[0.0, 0.0, g]]), with_tangent=False).stress[0, 2] for g in (h, -h)]
    assert G == pytest.approx((s[0] - s[1]) / (2 * h), rel=1e-3)
    assert G > 0.0


class _Stop(Exception):
    pass


@pytest.mark.parametrize("regularised", [False, True])
def test_checkpoint_resume_gives_the_uninterrupted_result_bit_for_bit(tmp_path, regularised):
    make = (lambda: SecondGradientSpecimen(2, 4, length=0.2, modulus=4e7)) if regularised else (
        lambda: fe.BiaxialSpecimen(2, 4))
    steps = programme(12)
    specimen = make()
    full = specimen.run(material_for(specimen), steps, scale=P0,
                        checkpoint=Checkpoint(tmp_path / "full.h5", 3, {"case": regularised}))
    checkpoint = Checkpoint(tmp_path / "c.h5", 3, {"case": regularised})

    def interrupt(k, result):
        if k == 10:
            raise _Stop

    specimen = make()
    with pytest.raises(_Stop):
        specimen.run(material_for(specimen), steps, scale=P0, progress=interrupt, checkpoint=checkpoint)
    assert checkpoint.steps_done() == 9
    specimen = make()
    resumed = specimen.run(material_for(specimen), steps, scale=P0, checkpoint=checkpoint)
    assert len(resumed) == len(full)
    for a, b in zip(full, resumed):
        assert (a.sigma11, a.sigma22, a.eps11, a.iterations, a.residuals) == (b.sigma11, b.sigma22, b.eps11,
                                                                            b.iterations, b.residuals)
        assert a.diagnostics == b.diagnostics  # the solver's counts too (second gradient: factorisations, ...)
        for name in ("displacement", "strain", "stress", "opening", "open_fraction"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_killed_run_resumes_to_the_same_files(tmp_path):
    """A run killed (SIGKILL) after a random checkpoint and resumed writes the uninterrupted run's fields."""
    argv = TINY + ["--eps-max", "0.02", "--imperfection", "0.2", "--length", "0.2", "--orientations", "24"]
    reference = tmp_path / "reference"
    assert cli(argv + ["--checkpoint-every", "1", "--out", str(reference)]) == 0
    out = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen([sys.executable, "-m", "homogenization.bvp", *argv, "--checkpoint-every", "1",
                                "--out", str(out), "-q"], cwd=ROOT, env=env)
    target = int(np.random.default_rng().integers(3, 18))
    checkpoint = Checkpoint(out / bvp.CHECKPOINT_FILE, 1, {})
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if checkpoint.exists() and checkpoint.steps_done() >= target:
                break
        except OSError:
            pass
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    killed_at = checkpoint.steps_done()
    assert killed_at < 25, "the run ended before it was killed"
    assert not (out / "curve.csv").exists()
    assert cli(argv + ["--checkpoint-every", "1", "--resume", "--out", str(out)]) == 0
    assert (out / "curve.csv").read_text() == (reference / "curve.csv").read_text()
    with h5py.File(reference / "run.h5") as a, h5py.File(out / "run.h5") as b:
        for name in ("displacement", "strain", "stress", "opening", "open_fraction"):
            np.testing.assert_array_equal(a["fields"][name][()], b["fields"][name][()])


def test_output_fields_for_paraview(tmp_path):
    out = tmp_path / "run"
    assert cli(TINY + ["--length", "0.2", "--out", str(out)]) == 0
    mesh = meshio.read(out / "vtu" / "step_0015.vtu")
    for name in ("p", "q", "mean_opening_deg", "open_contact_fraction", "deviatoric_strain"):
        assert name in mesh.cell_data, name
    opening = mesh.cell_data["mean_opening_deg"][0]
    assert np.all((opening > 30.0) & (opening < 60.0) & (np.abs(opening - 40.0) > 1e-3))  # moved from alpha0 = 40
    fraction = mesh.cell_data["open_contact_fraction"][0]
    assert np.all((fraction > 0.0) & (fraction < 1.0))
    assert mesh.cell_data["p"][0] == pytest.approx(np.full(32, P0 + 0.5 * mesh.cell_data["q"][0]), rel=2e-2)
    with h5py.File(out / "run.h5") as f:
        assert f["fields/opening"].shape == (15, 128)


def test_band_measurement_of_a_known_band():
    """A Gaussian band of FWHM 0.2 m at 60 deg on scattered points: width and angle recovered."""
    rng = np.random.default_rng(0)
    points = rng.uniform([0.0, 0.0], [1.0, 2.0], size=(20000, 2))
    d = np.array([np.cos(np.radians(60.0)), np.sin(np.radians(60.0))])
    s = (points - [0.5, 1.0]) @ np.array([-d[1], d[0]])
    sigma = 0.2 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    eps_d = 0.01 + 0.3 * np.exp(-0.5 * (s / sigma) ** 2)
    band = measure_band(points, np.full(len(points), 1e-4), eps_d, bin_width=0.01)
    assert band.angle_deg == pytest.approx(60.0, abs=1.0)
    assert band.width == pytest.approx(0.2, rel=0.05)
    assert band.background == pytest.approx(0.01, abs=0.01)


@pytest.mark.parametrize("extra, message", [
    (["--length", "0"], "argument --length: 0 must be > 0"),
    (["--length=-0.1"], "argument --length: -0.1 must be > 0"),
    (["--checkpoint-every", "0"], "argument --checkpoint-every: 0 must be >= 1"),
])
def test_bad_length_one_line_exit_2(tmp_path, capsys, extra, message):
    assert_usage_error(capsys, cli, TINY + extra + ["--out", str(tmp_path / "x")], message, tmp_path / "x")


def test_mesh_too_coarse_for_the_length_and_bad_resume(tmp_path, capsys):
    assert cli(TINY + ["--length", "0.005", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "--length 0.005: the expected band" in err and "use at least 3" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x").exists()
    # a larger length widens the band far less than 27 L (0.23 m measured at 15 mm): 8 x 16 elements of 0.125 m
    coarse = [*TINY[:TINY.index("--elements")], "--elements", "8,16", *TINY[TINY.index("--elements") + 2:]]
    assert cli(coarse + ["--length", "0.015", "--out", str(tmp_path / "z")]) == 2
    assert "the expected band (0.2 m wide) spans 1.6 elements" in capsys.readouterr().err
    assert cli(TINY + ["--resume", "--out", str(tmp_path / "y")]) == 2
    assert capsys.readouterr().err.strip().endswith(f"--resume: {tmp_path / 'y' / 'checkpoint.h5'} does not exist")


def test_resume_with_other_settings_is_refused(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli(TINY + ["--checkpoint-every", "5", "--out", str(out)]) == 0
    capsys.readouterr()
    before = (out / "curve.csv").read_bytes()
    assert cli(TINY + ["--p0", "3e5", "--checkpoint-every", "5", "--resume", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "was written with other settings (p0)" in err and err.count("\n") == 1, err
    # the interval sets when solver data are renewed: another one (or none) would not repeat the arithmetic
    assert cli(TINY + ["--resume", "--out", str(out)]) == 2
    assert "was written with other settings (checkpoint_every)" in capsys.readouterr().err
    assert (out / "curve.csv").read_bytes() == before


def test_backend_without_tangent_is_refused_before_any_step(tmp_path, capsys, monkeypatch):
    class NoTangent:
        def __init__(self, model):
            self._model = model
            self.name = "no-tangent"

        def __getattr__(self, name):
            return getattr(self._model, name)

        def step(self, state, d_eps_local):
            raise AssertionError("no step may run")

    real = bvp.make_cell_model
    monkeypatch.setattr(bvp, "make_cell_model", lambda *a, **k: NoTangent(real(*a, **k)))
    assert cli(TINY + ["--length", "0.2", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "returns no consistent tangent" in err and err.count("\n") == 1, err


def test_the_linear_solver_counts_are_reported_per_step_in_the_status_line_and_run_h5(tmp_path, capsys):
    """The second-gradient solver's factorisations, pivoting fallbacks and GMRES iterations: per step in run.h5's
    history, summed in the status line; none for a first-gradient run."""
    out = tmp_path / "run"
    assert cli(TINY + ["--length", "0.2", "--imperfection", "0.2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    with h5py.File(out / "run.h5") as f:
        counts = {name: f["history"][name][()] for name in ("factorisations", "pivoted_factorisations",
                                                           "krylov_iterations")}
    assert all(c.shape == (15,) and np.all(c >= 0) for c in counts.values())
    assert counts["factorisations"].sum() >= 1 and counts["krylov_iterations"].sum() >= 1
    assert (f"second-gradient solves: {int(counts['factorisations'].sum())} LU factorisations "
            f"({int(counts['pivoted_factorisations'].sum())} redone with pivoting), "
            f"{int(counts['krylov_iterations'].sum())} GMRES iterations") in printed
    plain = tmp_path / "plain"
    assert cli(TINY + ["--out", str(plain)]) == 0
    assert "second-gradient solves" not in capsys.readouterr().out
    with h5py.File(plain / "run.h5") as f:
        assert "factorisations" not in f["history"]


def test_a_pivot_free_factorisation_that_falls_short_is_counted_as_a_fallback(monkeypatch):
    """Where GMRES fails on the pivot-free factors, the step pivots and counts it: here every factorisation."""
    from homogenization.fe import second_gradient  # noqa: PLC0415

    gmres = second_gradient.spla.gmres

    def failing_after_factorisation(*args, **kwargs):
        x, info = gmres(*args, **kwargs)
        return x, (1 if "callback" not in kwargs else info)  # the solve right after a fresh pivot-free factorisation

    monkeypatch.setattr(second_gradient.spla, "gmres", failing_after_factorisation)
    specimen = SecondGradientSpecimen(2, 4, length=0.2, modulus=4e7)
    results = specimen.run(material_for(specimen), programme(4), scale=P0)
    per_step = {name: sum(r.diagnostics[name] for r in results)
                for name in ("factorisations", "pivoted_factorisations")}
    assert per_step["factorisations"] >= 1
    assert per_step["pivoted_factorisations"] == per_step["factorisations"] == specimen.pivoted_factorisations


@pytest.mark.parametrize("max_halvings", [4, 0])
def test_a_correction_that_raises_the_residual_is_halved_or_counted_as_taken(monkeypatch, max_halvings):
    """One Newton correction made three times too long raises the residual: it is halved (``line_search_halvings``),
    or, once the halvings are spent (none allowed here), taken all the same and counted in ``growths_taken``."""
    specimen = fe.BiaxialSpecimen(2, 4)
    exact, calls = specimen.newton_correction, []

    def overshooting(*args):
        calls.append(1)
        return exact(*args) * (3.0 if len(calls) == 12 else 1.0)

    monkeypatch.setattr(specimen, "newton_correction", overshooting)
    monkeypatch.setattr(fe, "MAX_HALVINGS", max_halvings)
    results = specimen.run(material_for(specimen), programme(), scale=P0)
    halved = sum(r.diagnostics["line_search_halvings"] for r in results)
    taken = sum(r.diagnostics["growths_taken"] for r in results)
    assert (halved > 0 and taken == 0) if max_halvings else (halved == 0 and taken == 1), (halved, taken)
