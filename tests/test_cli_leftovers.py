"""Nothing outside the output: no Dask scratch space left in TMPDIR; a status line "-> FILE"
only once FILE is in place."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from homogenization.cli import biaxial
from homogenization.output import figures
from warp_hcell.core import cli

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--alpha0", "55", "--eps-max", "0.002", "--increment", "5e-4", "--orientations", "12"]


def test_sweep_leaves_nothing_in_tmpdir_nor_beside_its_output(tmp_path):
    """Two cases on a LocalCluster of two workers (what the default --workers gives on two cores)."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg", "TMPDIR": str(scratch)}
    argv = ["--backend", "analytical", "--p0", "2e5,5.85e6", "--eps-max", "0.002", "--increment", "5e-4",
            "--orientations", "12", "-q", "--workers", "2", "--out", str(out)]
    done = subprocess.run([sys.executable, "-m", "homogenization.sweep", *argv], capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "tmp"]
    assert list(scratch.iterdir()) == []
    assert len(list((out / "cases").iterdir())) == 2


def test_a_dask_cluster_keeps_its_scratch_in_its_own_folder_and_removes_it(tmp_path, monkeypatch):
    from warp_hcell.core.execution import DaskExecution

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)  # read TMPDIR again
    with DaskExecution(workers=1) as dask:
        assert [item for item, _ in dask.map(pow, 2, [3])] == [3]
        (folder,) = tmp_path.iterdir()
        assert folder.name.startswith("hmodel-dask-") and (folder / "dask-scratch-space").is_dir()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("existing", [False, True], ids=["new", "overwrite"])
def test_no_status_line_when_the_output_fails_after_the_run_file(existing, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    if existing:
        assert cli.run_main(biaxial.main, [*TINY, "-q", "--out", str(out)]) == 0
    before = sorted(p.name for p in out.iterdir()) if existing else None

    def disk_full(fig, path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(figures, "save_figure", disk_full)
    assert cli.run_main(biaxial.main, [*TINY, "--overwrite", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert "->" not in captured.out and "No space left on device" in captured.err
    assert (sorted(p.name for p in out.iterdir()) if existing else out.exists()) == (before if existing else False)


def test_status_lines_follow_the_swap(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli.run_main(biaxial.main, [*TINY, "--backend", "analytical,ann", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == ["analytical", "ann", "figure -> " + str(out / "cambridge.png")]
    for line in lines[:2]:
        assert all(Path(path).is_file() for path in line.split(" -> ")[1].split(", "))
