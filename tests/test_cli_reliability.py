"""Honest failures of every CLI: each bad case is exit 2 and one line on stderr, leaves the
existing output byte-identical and no stray files next to it.

Cases: --device cuda without a GPU (every CLI), increments a backend cannot do, an ANN path
row of -0.9, clean on a file without outputs, train with an unwritable --out and Ctrl-C, a
second run on a busy output, a biaxial run killed while writing; calibrate with --out under a
file, Ctrl-C in its sampler (one line, the chain resumes) and its lock; the temporary file of
a final write killed by SIGKILL, removed by the next run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from homogenization.calibration import bayes
from homogenization.cli import biaxial, calibrate, cell, hmodel
from training import fitting, train
from warp_hcell.core import cli, files
from warp_hcell.database import format as database
from warp_hcell import clean as clean_command, generate as generate_command

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--alpha0", "55", "--eps-max", "0.01", "--increment", "5e-4", "--orientations", "12", "-q"]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative name -> bytes), hidden ones included."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "error:" in lines[0] and "Traceback" not in err
    return lines[0]


@pytest.fixture
def previous_run(tmp_path) -> Path:
    """A finished biaxial run in tmp_path/run, and nothing else in tmp_path."""
    out = tmp_path / "run"
    assert cli.run_main(biaxial.main, TINY + ["--out", str(out)]) == 0
    return out


@pytest.fixture
def no_gpu(monkeypatch):
    monkeypatch.setattr(cli, "cuda_device_count", lambda: 0)


@pytest.mark.parametrize("command, argv", [
    ("biaxial", ["--backend", "dem", "--out", "OUT"]),
    ("cell", ["--backend", "dem", "--path", "PATH", "--out", "OUT/cell.csv"]),
    ("generate", ["--samples", "10", "--out", "OUT/db.h5"]),
    ("train", ["--data", "PATH", "--out", "OUT/model.pt"]),
])
def test_cuda_without_gpu_is_one_line_in_every_cli(command, argv, previous_run, no_gpu, capsys):
    before = snapshot(previous_run.parent)
    argv = [a.replace("OUT", str(previous_run)).replace("PATH", str(previous_run / "curve.csv")) for a in argv]
    start = time.perf_counter()
    assert hmodel.main([command, *argv, "--device", "cuda", "--overwrite"]) == 2
    assert time.perf_counter() - start < 5.0  # refused before any heavy work
    assert one_error_line(capsys) == f"hmodel {command}: error: --device cuda: no CUDA GPU on this machine; use --device cpu"
    assert snapshot(previous_run.parent) == before


def test_cuda_index_beyond_the_machine(monkeypatch):
    monkeypatch.setattr(cli, "cuda_device_count", lambda: 1)
    assert cli.device_name("cuda:0") == "cuda:0"
    with pytest.raises(cli.UserError, match=r"has 1 CUDA GPU\(s\), cuda:0 to cuda:0"):
        cli.device_name("cuda:1")


@pytest.mark.parametrize("argv, message", [
    (["--increment", "1", "--eps-max", "0.2"], "--increment 1 is larger than --eps-max 0.2"),
    (["--iso-increment", "0.5"], "--iso-increment 0.5 must be < 0.1"),
])
def test_increment_a_backend_cannot_do_is_refused(argv, message, previous_run, capsys):
    before = snapshot(previous_run.parent)
    assert cli.run_main(biaxial.main, ["--backend", "analytical,ann", *argv, "--out", str(previous_run),
                                       "--overwrite"]) == 2
    assert message in one_error_line(capsys)
    assert snapshot(previous_run.parent) == before


def test_coarse_increment_runs_with_one_warning(tmp_path, capsys):
    out = tmp_path / "coarse"
    assert cli.run_main(biaxial.main, ["--increment", "2e-3", "--eps-max", "0.02", "--orientations", "12", "-q",
                                       "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning: step 'shear' has strain increments up to 0.002 > 0.001" in err[0]


def test_ann_path_row_beyond_training_range_is_refused(tmp_path, capsys):
    path = tmp_path / "path.csv"
    path.write_text("d_eps_n,d_eps_t\n1e-4,0\n-0.9,0\n")
    out = tmp_path / "cell.csv"
    out.write_text("keep")
    assert cli.run_main(cell.main, ["--backend", "ann", "--path", str(path), "--out", str(out), "--overwrite"]) == 2
    line = one_error_line(capsys)
    assert f"{path} line 3: |d_eps| = 0.9 exceeds 0.001" in line
    assert out.read_text() == "keep" and sorted(p.name for p in tmp_path.iterdir()) == ["cell.csv", "path.csv"]


def test_clean_on_a_file_without_outputs(tmp_path, capsys):
    path = tmp_path / "db.h5"
    with h5py.File(path, "w") as f:  # a database header with probes but no states
        f.attrs["format"], f.attrs["format_version"] = database.FORMAT, database.FORMAT_VERSION
        f.create_dataset("d_eps", data=[[0.0, 1e-4]])
    before = path.read_bytes()
    assert clean_command.main([str(path)]) == 2
    assert "not a complete learning database" in one_error_line(capsys)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["db.h5"]


def test_train_checks_out_before_reading_the_data(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert train.run(["--data", str(tmp_path / "missing.h5"), "--out", str(blocker / "model.pt")]) == 2
    assert f"{blocker} is not a folder" in one_error_line(capsys)


def test_train_ctrl_c_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    planar_database = SimpleNamespace(schema=SimpleNamespace(dim=2))
    monkeypatch.setattr(fitting, "load_database", lambda path: planar_database)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fitting, "fit", interrupted)
    assert train.run(["--data", "db.h5", "--out", str(tmp_path / "model.pt")]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["hmodel: interrupted"]
    assert list(tmp_path.iterdir()) == []


def test_second_run_on_a_busy_output_exits_2(previous_run, tmp_path, capsys):
    before = snapshot(tmp_path)
    with files.output_lock(previous_run):
        assert cli.run_main(biaxial.main, TINY + ["--out", str(previous_run), "--overwrite"]) == 2
        assert "is being written by another run" in one_error_line(capsys)
        model = tmp_path / "model.pt"
        with files.output_lock(model):
            assert train.run(["--data", "db.h5", "--out", str(model)]) == 2
            assert "is being written by another run" in one_error_line(capsys)
    assert snapshot(tmp_path) == before  # the lock files went with the locks


def test_overwrite_replaces_the_output_set_as_a_unit(previous_run, tmp_path):
    (previous_run / "analytical").mkdir()  # a folder of an earlier overlay run: dropped with the set
    assert cli.run_main(biaxial.main, TINY + ["--p0", "2e5", "--out", str(previous_run), "--overwrite"]) == 0
    assert sorted(p.name for p in previous_run.iterdir()) == ["cambridge.png", "curve.csv", "run.h5"]
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_overwrite_refuses_a_folder_with_foreign_files(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert cli.run_main(biaxial.main, TINY + ["--out", str(tmp_path), "--overwrite"]) == 2
    assert "holds files that this command did not write (notes.txt)" in one_error_line(capsys)
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def _start_long_run(out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    argv = ["--alpha0", "55", "--eps-max", "0.2", "--increment", "1e-5", "--orientations", "360", "-q",
            "--out", str(out), "--overwrite"]
    # SIGINT at its default in the child: a shell starts background jobs with SIGINT ignored, and a
    # Python started so installs no KeyboardInterrupt handler (a suite run with `&` then failed here)
    return subprocess.Popen([sys.executable, "-m", "homogenization.biaxial", *argv], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(path: Path, process: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_run_keeps_the_previous_output_and_leaves_nothing(sig, previous_run, tmp_path):
    before = snapshot(tmp_path)
    process = _start_long_run(previous_run)
    _wait_for(tmp_path / ".run.partial", process)
    process.send_signal(sig)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130 and err.strip().splitlines() == ["python -m homogenization.biaxial: interrupted"]
    assert snapshot(tmp_path) == before


def test_killed_run_keeps_the_previous_output_and_the_next_run_cleans_up(previous_run, tmp_path):
    before = snapshot(previous_run)
    process = _start_long_run(previous_run)
    _wait_for(tmp_path / ".run.partial", process)
    process.kill()
    process.communicate(timeout=60)
    assert snapshot(previous_run) == before
    assert cli.run_main(biaxial.main, TINY + ["--out", str(previous_run), "--overwrite"]) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_output_folder_swaps_in_the_new_set(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(files, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with files.output_folder(out) as work:
        assert not (out / "new.txt").exists()
        (work / "new.txt").write_text("new")
    assert [p.name for p in out.iterdir()] == ["new.txt"] and [p.name for p in tmp_path.iterdir()] == ["out"]
    with pytest.raises(RuntimeError), files.output_folder(out) as work:
        (work / "half.txt").write_text("half")
        raise RuntimeError
    assert [p.name for p in out.iterdir()] == ["new.txt"] and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_output_folder_restores_a_set_left_between_the_two_renames(tmp_path):
    out = tmp_path / "out"
    stranded = tmp_path / ".out.replaced"  # killed after renaming the old set away
    stranded.mkdir()
    (stranded / "run.h5").write_text("previous")
    with pytest.raises(KeyboardInterrupt), files.output_folder(out):
        raise KeyboardInterrupt
    assert (out / "run.h5").read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == ["out"]


# -- calibrate ---------------------------------------------------------------------------------
CALIBRATION_DATA = "# test = undrained\n# p0 = 3e6\neps1,q\n0.004,1.1e6\n0.008,1.8e6\n0.012,2.2e6\n"


def calibrate_argv(tmp_path: Path, out: Path, steps: int) -> list[str]:
    data = tmp_path / "u.csv"
    if not data.exists():
        data.write_text(CALIBRATION_DATA)
    return ["calibrate", "--data", str(data), "--params", "phi_g,alpha0", "--walkers", "4", "--steps", str(steps),
            "--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none", "-q",
            "--out", str(out)]


def test_calibrate_out_under_a_file_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    assert hmodel.main(calibrate_argv(tmp_path, blocker / "out", 2)) == 2
    assert one_error_line(capsys) == (f"hmodel calibrate: error: cannot write to {blocker / 'out'}: {blocker} "
                                      f"is not a folder")
    assert blocker.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["blocker", "u.csv"]


def read_chain(out: Path) -> np.ndarray:
    with h5py.File(out / calibrate.CHAIN_FILE, "r") as fh:
        return fh["mcmc/chain"][()]


def test_calibrate_ctrl_c_is_one_line_and_the_chain_resumes(tmp_path, capsys, monkeypatch):
    assert hmodel.main(calibrate_argv(tmp_path, tmp_path / "whole", 4)) == 0
    capsys.readouterr()
    calls = {"n": 0}
    real = bayes.Posterior.__call__

    def interrupted_at_the_sixth_call(self, x):
        calls["n"] += 1
        if calls["n"] == 6:  # during the sampler's third step (the first call places the walkers)
            raise KeyboardInterrupt
        return real(self, x)

    monkeypatch.setattr(bayes.Posterior, "__call__", interrupted_at_the_sixth_call)
    out = tmp_path / "split"
    assert hmodel.main(calibrate_argv(tmp_path, out, 4)) == 130
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == ["hmodel calibrate: interrupted"] and "emcee" not in captured.out
    with h5py.File(out / calibrate.CHAIN_FILE, "r") as fh:
        done = int(fh["mcmc"].attrs["iteration"])
    assert sorted(p.name for p in out.iterdir()) == ["chain.h5"] and 0 < done < 4
    np.testing.assert_array_equal(read_chain(out)[:done], read_chain(tmp_path / "whole")[:done])
    monkeypatch.undo()
    assert hmodel.main(calibrate_argv(tmp_path, out, 4)) == 0  # the same command resumes
    np.testing.assert_array_equal(read_chain(out), read_chain(tmp_path / "whole"))
    assert not list(tmp_path.glob(".*"))


def test_calibrate_on_a_chain_killed_while_written_is_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / calibrate.CHAIN_FILE).write_bytes(b"\x89HDF\r\n half a file")
    assert hmodel.main(calibrate_argv(tmp_path, out, 2)) == 2
    assert one_error_line(capsys).endswith("chain.h5 is unreadable (a run killed while writing it?); add --overwrite "
                                           "to restart the chain")
    assert (out / calibrate.CHAIN_FILE).read_bytes() == b"\x89HDF\r\n half a file"


def test_second_calibration_on_a_busy_folder_exits_2(tmp_path, capsys):
    out = tmp_path / "run"
    with files.output_lock(out):
        assert hmodel.main(calibrate_argv(tmp_path, out, 2)) == 2
        assert "is being written by another run" in one_error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["u.csv"]


# -- temporaries of a killed final write ------------------------------------------------------------
def kill_while_writing(path: Path) -> Path:
    """Run a process that SIGKILLs itself inside ``atomic_write(path)``; returns the temporary it left."""
    code = ("import os, signal, sys\nfrom pathlib import Path\nfrom warp_hcell.core.files import atomic_write\n"
            "with atomic_write(Path(sys.argv[1])) as tmp:\n    tmp.write_bytes(bytes(4096))\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    done = subprocess.run([sys.executable, "-c", code, str(path)], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, timeout=120)
    assert done.returncode == -signal.SIGKILL
    (left,) = path.parent.glob(f".{path.name}.*.tmp")
    return left


def test_the_temporary_of_a_killed_final_write_is_removed_by_the_next_run(tmp_path):
    out = tmp_path / "db.h5"
    left = kill_while_writing(out)
    other = tmp_path / ".db.h5.x.abcdefgh.tmp"  # another output's temporary, and a file of the user
    other.write_text("not ours")
    (tmp_path / "notes.tmp").write_text("mine")
    argv = ["--mesostructure", str(ROOT / "warp_hcell" / "data" / "h_cell_lateral_0.7D.toml"), "--samples", "100",
            "--chunk-size", "100", "--n-directions", "4", "--threads", "1", "-q", "--out", str(out)]
    assert generate_command.main(argv) == 0
    assert not left.exists() and other.read_text() == "not ours" and (tmp_path / "notes.tmp").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".db.h5.x.abcdefgh.tmp", "db.h5", "notes.tmp"]


def test_the_lock_of_a_folder_removes_the_temporaries_of_its_files(tmp_path):
    out = tmp_path / "calibration"
    out.mkdir()
    left = kill_while_writing(out / "posterior.h5")
    (out / "chain.h5").write_text("kept")
    with files.output_lock(out):
        assert not left.exists() and (out / "chain.h5").read_text() == "kept"


def test_a_python_warning_in_a_command_is_one_line():
    """Python's warning display (file, line and source: two lines), not pytest's capture, hence a process."""
    code = ("import warnings; from warp_hcell.core import cli\n"
            "def main(argv):\n    warnings.warn('a warning\\n  over two lines', RuntimeWarning)\n"
            "before = warnings.formatwarning\nassert cli.run_main(main, []) == 0\n"
            "assert warnings.formatwarning is before")
    done = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stderr == "hmodel: warning: a warning over two lines\n", done.stderr


def test_a_kill_lost_in_a_destructor_is_delivered_again():
    """Python ignores a KeyboardInterrupt raised inside ``__del__`` or a weakref callback (Warp's arrays have them):
    a ``kill`` of a DEM run was lost there and the run went on to exit 0; the signal is sent again."""
    class Swallowing:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.1)  # the handler runs here, and its KeyboardInterrupt is ignored

    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        with files.sigterm_as_interrupt():
            Swallowing()
            time.sleep(5.0)
    assert time.monotonic() - start < 3.0
