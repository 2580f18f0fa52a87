"""Checkpoints of an element test (``element_test.checkpoint``): a run killed after any increment and run again
from its checkpoint gives the uninterrupted run's record bit for bit (analytical 2D and 3D with the
critical-state renewal, DEM, shipped ANN), a finished checkpoint gives the record without a step, and a
checkpoint of other settings is refused."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import h5py
import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.backends.analytical import AnalyticalCell
from homogenization.element_test import driver, programme as programmes
from homogenization.cli import biaxial
from homogenization.output import io
from homogenization.element_test.checkpoint import RunCheckpoint
from homogenization.material.critical_state import CriticalState
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.core import cli
from warp_hcell.core.errors import UserError
from warp_hcell.mesostructures.hcell import h_cell, plain_h_cell

LAW = ContactLaw()
ROOT = Path(__file__).resolve().parents[1]


class Stop(Exception):
    """Raised by the progress callback in place of a kill."""


def stopping_at(k_stop: int | None):
    """A ``progress`` that raises ``Stop`` at the increment after the first ``k_stop`` (over all stages), before its
    checkpoint: a checkpoint after every increment then holds ``k_stop``."""
    count = [0]

    @contextlib.contextmanager
    def progress(plan, done=0):
        def advance(_plan, _points):
            count[0] += 1
            if k_stop is not None and count[0] == k_stop + 1:
                raise Stop
        yield advance
    return progress


def assert_same_record(a, b) -> None:
    for f in fields(a):
        if f.name in ("step_seconds", "programme", "density_map"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, dict):
            assert list(x) == list(y), f.name
            for name in x:
                assert np.asarray(x[name]).tobytes() == np.asarray(y[name]).tobytes(), (f.name, name)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f.name
        else:
            assert x == y, f.name


def interrupted_then_resumed(run, tmp_path, k_stop: int):
    """The record of ``run(progress, checkpoint)`` stopped at increment ``k_stop`` and run again."""
    path = tmp_path / "run.ckpt.h5"
    with pytest.raises(Stop):
        run(stopping_at(k_stop), RunCheckpoint(path, {"case": 1}, 0.0))
    assert path.is_file()
    again = RunCheckpoint(path, {"case": 1}, 0.0)
    assert again.progress()[0] == k_stop
    return run(stopping_at(None), again)


def test_a_2d_run_resumes_bit_for_bit_at_any_increment(tmp_path):
    programme = programmes.biaxial(3e6, 0.01, 1e-3, iso_increment=1e-3, drained=True)
    model = AnalyticalCell(LAW, 0.5)

    def run(progress, checkpoint):
        return driver.run(model, programme, mesostructure=h_cell(55.0, 0.5), n_orientations=24,
                          snapshot_interval=3, progress=progress, checkpoint=checkpoint)

    whole = run(False, None)
    n_iso = int((whole.stage == whole.stage[0]).sum())
    for k_stop in (1, n_iso, n_iso + 4):  # inside the isotropic stage, at its end, inside the shear
        folder = tmp_path / str(k_stop)
        folder.mkdir()
        assert_same_record(interrupted_then_resumed(run, folder, k_stop), whole)
    # a finished checkpoint gives the record at once, and one of other settings is refused
    path = tmp_path / str(n_iso + 4) / "run.ckpt.h5"
    assert RunCheckpoint(path, {"case": 1}, 0.0).progress() == (whole.n_increments, len(programme))
    assert_same_record(run(stopping_at(1), RunCheckpoint(path, {"case": 1}, 0.0)), whole)
    with pytest.raises(UserError, match=r"other settings \(case\)"):
        run(False, RunCheckpoint(path, {"case": 2}, 0.0))


def test_a_3d_run_with_renewals_resumes_bit_for_bit(tmp_path):
    programme = programmes.triaxial(2e5, 0.02, 1e-3, iso_increment=2e-4, test="undrained")
    model = make_cell_model("analytical", contact_law=LAW, radius=0.5, dim=3)
    rule = CriticalState()

    def run(progress, checkpoint):
        return driver.run(model, programme, mesostructure=plain_h_cell(3, 55.0, 0.5), lebedev_order=11, n_spins=4,
                          critical_state=rule, progress=progress, checkpoint=checkpoint)

    whole = run(False, None)
    assert whole.diagnostics["critical_state_renewals"][-1] > 0
    n_iso = int((whole.stage == whole.stage[0]).sum())
    assert_same_record(interrupted_then_resumed(run, tmp_path, n_iso + 7), whole)


@pytest.mark.parametrize("backend, dim", [("dem", 2), ("ann", 2), ("ann", 3)])
def test_dem_and_ann_runs_resume_bit_for_bit(tmp_path, backend, dim):
    """The DEM's state round trip (positions, velocities, contact history) and the ANN's out-of-distribution
    counts, each run with a new model as a new process has."""
    programme = (programmes.biaxial(1e6, 2e-3, 2e-4, iso_increment=2e-4) if dim == 2 else
                 programmes.triaxial(2e5, 2e-3, 1e-4, iso_increment=1e-4, test="drained"))
    cells = {"mesostructure": plain_h_cell(dim, 55.0, 0.5), "n_orientations": 6, "lebedev_order": 11, "n_spins": 4}
    models = []

    def run(progress, checkpoint):
        models.append(make_cell_model(backend, contact_law=LAW, radius=0.5, dim=dim))
        return driver.run(models[-1], programme, progress=progress, checkpoint=checkpoint, **cells)

    whole = run(False, None)
    n_iso = int((whole.stage == whole.stage[0]).sum())
    assert_same_record(interrupted_then_resumed(run, tmp_path, n_iso + 3), whole)
    if backend == "ann":
        assert models[0].ood_counts[1] > 0
        assert models[-1].ood_counts.tolist() == models[0].ood_counts.tolist()
        # from the last increment's checkpoint: no step taken, and which code ran the step is still known (run.h5)
        assert_same_record(run(stopping_at(None), RunCheckpoint(tmp_path / "run.ckpt.h5", {"case": 1}, 0.0)), whole)
        assert models[-1].fast.step_path == models[0].fast.step_path is not None


def run_h5(path: Path) -> dict[str, bytes]:
    """Every dataset and attribute of a run file as bytes, but the command line and the git revision."""
    out = {}
    with h5py.File(path) as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = repr(obj[()].tolist()).encode()
            out.update({f"{name}@{k}": repr(obj.attrs[k]).encode() for k in obj.attrs})
        f.visititems(visit)
        out.update({f"@{k}": repr(f.attrs[k]).encode() for k in f.attrs if k not in ("command", "git_revision")})
    return out


def test_a_killed_biaxial_command_resumes_with_the_uninterrupted_result(tmp_path, capsys):
    """SIGTERM during the DEM's shear, after the analytical backend finished: one line, exit 130, the checkpoints
    kept; the same command resumes both backends (the finished one without a step) and writes the uninterrupted
    run's files; a changed command is refused in one line until --restart discards the checkpoints."""
    argv = ["--backend", "analytical,dem", "--orientations", "6", "--p0", "1e6", "--eps-max", "0.02",
            "--increment", "2e-5", "--checkpoint-seconds", "0.01", "-q"]
    assert cli.run_main(biaxial.main, [*argv[:-3], "-q", "--out", str(tmp_path / "whole")]) == 0  # saves nothing
    n_total = io.read_run(tmp_path / "whole" / "dem").record.n_increments
    out, resume = tmp_path / "cut", tmp_path / ".cut.resume"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    # the DEM's shear takes ~0.1 s: saved every 0.01 s and looked at every 0.005 s (it could finish between two looks)
    process = subprocess.Popen([sys.executable, "-m", "homogenization.biaxial", *argv, "--out", str(out)], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (resume / "dem.h5").exists() or RunCheckpoint(resume / "dem.h5", {}, 0).progress()[1] < 1:
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.005)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130
    assert err.strip().splitlines() == [f"python -m homogenization.biaxial: interrupted; the same command resumes "
                                        f"from {resume}"]
    assert not out.exists() and sorted(p.name for p in resume.iterdir()) == ["analytical.h5", "dem.h5"]
    done, stages = RunCheckpoint(resume / "dem.h5", {}, 0).progress()
    assert stages == 1 and done < n_total  # stopped inside the shear

    changed = [("4e-5" if value == "2e-5" else value) for value in argv]  # another --increment
    assert cli.run_main(biaxial.main, [*changed, "--out", str(out)]) == 2
    assert "other settings (flags.increment, programme.steps): run that command again to resume it, or add " \
        "--restart" in capsys.readouterr().err
    assert cli.run_main(biaxial.main, [*argv[2:], "--backend", "dem", "--out", str(out)]) == 2  # not the analytical's
    assert "holds the checkpoint of an interrupted run of other backends (analytical)" in capsys.readouterr().err
    shutil.copytree(resume, tmp_path / ".other.resume")
    assert cli.run_main(biaxial.main, [*argv, "--out", str(out)]) == 0
    assert not resume.exists()
    assert cli.run_main(biaxial.main, [*changed, "--restart", "--out", str(tmp_path / "other")]) == 0
    assert not (tmp_path / ".other.resume").exists()
    for backend in ("analytical", "dem"):
        assert run_h5(out / backend / "run.h5") == run_h5(tmp_path / "whole" / backend / "run.h5")
        assert (out / backend / "curve.csv").read_bytes() == (tmp_path / "whole" / backend / "curve.csv").read_bytes()


def test_a_run_it_cannot_keep_runs_without_a_checkpoint_and_says_so(tmp_path):
    """A renewal rule other than the critical-state one (here one that renews nothing) may hold state that the
    checkpoint does not know: the run goes on without one, with a warning."""
    class Unknown:
        def within(self, start, update):
            return update

        def advance(self, state):
            return state

    programme = programmes.biaxial(1e6, 1e-3, 1e-4, iso_increment=1e-4)
    path = tmp_path / "run.ckpt.h5"
    with pytest.warns(RuntimeWarning, match="keeps no checkpoint: its rule Unknown changes the cells' laws"):
        record = driver.run(AnalyticalCell(LAW, 0.5), programme, mesostructure=h_cell(55.0, 0.5), n_orientations=6,
                            renewal=lambda points: Unknown(), checkpoint=RunCheckpoint(path, {}, 0.0))
    assert record.n_increments > 10 and not path.exists()


def test_a_backend_that_others_follow_keeps_its_last_increment(tmp_path):
    """Without ``keep_last`` a run shorter than the interval saves nothing; with it (every backend of a command
    but the last) its finished state is kept, so an interruption in a later backend does not run it again."""
    programme = programmes.biaxial(1e6, 1e-3, 1e-4, iso_increment=1e-4)
    for keep in (False, True):
        checkpoint = RunCheckpoint(tmp_path / f"{keep}.h5", {}, 1e9)
        checkpoint.keep_last = keep
        record = driver.run(AnalyticalCell(LAW, 0.5), programme, mesostructure=h_cell(55.0, 0.5), n_orientations=6,
                            checkpoint=checkpoint)
        assert checkpoint.exists() == keep
    assert checkpoint.progress() == (record.n_increments, len(programme))


def test_the_key_holds_the_cells_geometry_and_the_model_files(tmp_path):
    """An edited mesostructure file (same path) or ANN sidecar file resumed a checkpoint of the old ones."""
    import json

    from homogenization.cli.run_files import run_checkpoints

    args = biaxial.build_parser().parse_args(["--out", str(tmp_path / "run")])
    programme = programmes.biaxial(1e6, 1e-3, 1e-4)
    models, options = {"analytical": AnalyticalCell(LAW, 0.5)}, {"analytical": {}}
    keys = [json.loads(run_checkpoints(args, models, options, LAW, h_cell(a, 0.5), programme)["analytical"].key)
            for a in (55.0, 56.0)]
    assert keys[0]["mesostructure_sha256"] != keys[1]["mesostructure_sha256"]
    ann = make_cell_model("ann", contact_law=LAW, radius=0.5)
    key = json.loads(run_checkpoints(args, {"ann": ann}, {"ann": {}}, LAW, h_cell(55.0, 0.5), programme)["ann"].key)
    assert {name.endswith("_ood.npz") for name in key["model_files"]} == {True, False}


def test_a_file_given_as_a_flag_is_keyed_by_its_content(tmp_path):
    """A --posterior (or any file flag) rewritten between the interrupted run and the rerun resumed and mixed them."""
    import json

    from homogenization.cli.run_files import run_checkpoints

    given = tmp_path / "programme.json"
    models, options = {"analytical": AnalyticalCell(LAW, 0.5)}, {"analytical": {}}
    keys = []
    for text in ("one", "two"):
        given.write_text(text)
        args = biaxial.build_parser().parse_args(["--out", str(tmp_path / "run"), "--programme", str(given)])
        checkpoint = run_checkpoints(args, models, options, LAW, h_cell(55.0, 0.5), programmes.biaxial(1e6, 1e-3, 1e-4))
        keys.append(json.loads(checkpoint["analytical"].key)["flags"]["programme"])
    assert keys[0]["path"] == keys[1]["path"] and keys[0]["sha256"] != keys[1]["sha256"]


def test_a_resumed_ann_run_says_the_out_of_distribution_warning_of_the_interrupted_one(tmp_path):
    """The warning is said once per run, when the cumulative fraction first exceeds the threshold: a run resumed after
    it says it again (its restored counts are past it), as the user of the resumed process would otherwise not know."""
    programme = programmes.biaxial(1e6, 0.3, 5e-3, iso_increment=2e-4)  # 30 % strain: far beyond the database

    def run(progress, checkpoint):
        model = make_cell_model("ann", contact_law=LAW, radius=0.5, dim=2, ood_interval=1)
        return driver.run(model, programme, mesostructure=plain_h_cell(2, 55.0, 0.5), n_orientations=6,
                          progress=progress, checkpoint=checkpoint)

    with pytest.warns(RuntimeWarning, match="beyond the out-of-distribution threshold"):
        whole = run(False, None)
    path = tmp_path / "run.ckpt.h5"
    with pytest.warns(RuntimeWarning, match="beyond the out-of-distribution threshold"), pytest.raises(Stop):
        run(stopping_at(whole.n_increments - 2), RunCheckpoint(path, {"case": 1}, 0.0))
    with pytest.warns(RuntimeWarning, match="beyond the out-of-distribution threshold"):
        assert_same_record(run(stopping_at(None), RunCheckpoint(path, {"case": 1}, 0.0)), whole)


def test_an_interruption_while_the_figure_is_drawn_says_where_the_command_resumes(tmp_path, capsys, monkeypatch):
    """After the runs, before the output is in place (band, figure), the checkpoints are still there: the one line
    says so, and the same command then writes the output from them."""
    from homogenization.output import figures  # noqa: PLC0415

    argv = ["--backend", "analytical", "--orientations", "6", "--p0", "1e6", "--eps-max", "2e-3", "--increment",
            "2e-4", "--checkpoint-seconds", "0", "-q", "--out", str(tmp_path / "run")]
    save = figures.save_figure

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(figures, "save_figure", interrupted)
    assert cli.run_main(biaxial.main, argv) == 130
    resume = tmp_path / ".run.resume"
    assert capsys.readouterr().err.strip().endswith(f"interrupted; the same command resumes from {resume}")
    assert (resume / "analytical.h5").is_file() and not (tmp_path / "run").exists()
    monkeypatch.setattr(figures, "save_figure", save)
    assert cli.run_main(biaxial.main, argv) == 0
    assert (tmp_path / "run" / "curve.csv").is_file() and not resume.exists()


def test_a_dem_run_resumes_under_other_threads_and_an_ann_run_does_not(tmp_path, capsys, monkeypatch):
    """The DEM's results do not depend on --threads (its cells are independent of the chunks): its checkpoint resumes
    under another --threads, to the uninterrupted run's files; the ANN's (a torch tangent) is refused."""
    from homogenization.output import figures  # noqa: PLC0415

    common = ["--orientations", "4", "--p0", "1e6", "--eps-max", "1e-3", "--increment", "2e-4", "--checkpoint-seconds",
              "0", "-q"]
    assert cli.run_main(biaxial.main, ["--backend", "dem", *common, "--threads", "1", "--out", str(tmp_path / "whole")]) == 0
    save = figures.save_figure

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    for backend, resumes in (("dem", True), ("ann", False)):
        argv = ["--backend", backend, *common, "--out", str(tmp_path / backend)]
        monkeypatch.setattr(figures, "save_figure", interrupted)
        assert cli.run_main(biaxial.main, [*argv, "--threads", "1"]) == 130
        monkeypatch.setattr(figures, "save_figure", save)
        capsys.readouterr()
        assert cli.run_main(biaxial.main, [*argv, "--threads", "2"]) == (0 if resumes else 2)
        err = capsys.readouterr().err
        assert ("flags.threads" in err) != resumes, err
    assert (tmp_path / "dem" / "curve.csv").read_bytes() == (tmp_path / "whole" / "curve.csv").read_bytes()
