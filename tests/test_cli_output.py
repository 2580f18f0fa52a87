"""What the commands print: no Warp start-up messages without -v, progress bars that count
the increments as they run and, where stderr is no terminal, write plain lines (no carriage
returns); -q leaves warnings and errors only."""

from __future__ import annotations

import csv
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from warp_hcell.core import cli

ROOT = Path(__file__).resolve().parents[1]
LATERAL = ROOT / "warp_hcell" / "data" / "h_cell_lateral_0.7D.toml"
BANNER = re.compile(r"^Warp \d+\.\d+", re.MULTILINE)
"""Warp's start-up banner ("Warp 1.19.0 initialized:")."""


def run(argv: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m argv`` with stdout and stderr piped (no terminal)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, env=env, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done


def warp_talk(done: subprocess.CompletedProcess) -> list[str]:
    """Warp's start-up banner and its "no CUDA driver" warning, where printed."""
    text = done.stdout + done.stderr
    return [found for found in (BANNER.search(text), re.search("CUDA driver", text)) if found]


@pytest.fixture(scope="module")
def database(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("db") / "db.h5"
    run(["warp_hcell.generate", "--mesostructure", str(LATERAL), "--samples", "60", "--chunk-size", "60",
         "--n-directions", "4", "--threads", "1", "--out", str(out)])
    return out


def commands(tmp: Path, database: Path) -> dict[str, list[str]]:
    """Tiny runs of the three commands that start Warp (train: in its rollout)."""
    return {
        "generate": ["warp_hcell.generate", "--mesostructure", str(LATERAL), "--samples", "60", "--chunk-size", "60",
                     "--n-directions", "4", "--threads", "1", "--out", str(tmp / "db.h5")],
        "train": ["training.train", "--data", str(database), "--epochs", "1", "--hidden", "4", "--threads", "1",
                  "--out", str(tmp / "m.pt")],
        "biaxial": ["homogenization.biaxial", "--backend", "dem", "--threads", "1", "--alpha0", "55", "--eps-max",
                    "0.001", "--increment", "5e-4", "--orientations", "4", "--out", str(tmp / "b")],
    }


@pytest.mark.parametrize("command", ["generate", "train", "biaxial"])
def test_warp_is_silent_unless_verbose(command, database, tmp_path):
    quiet = run(commands(tmp_path / "quiet", database)[command])
    assert warp_talk(quiet) == [], quiet.stdout + quiet.stderr
    if command != "train":  # -v: every command's verbosity_parser, checked on the two cheaper runs (train: ~6 CPU-s)
        verbose = run([*commands(tmp_path / "verbose", database)[command], "-v"])
        assert BANNER.search(verbose.stdout + verbose.stderr)


def test_piped_progress_is_plain_lines_that_count_the_isotropic_increments(tmp_path):
    out = tmp_path / "run"
    done = run(["homogenization.biaxial", "--alpha0", "55", "--eps-max", "0.002", "--increment", "5e-4",
                "--orientations", "12", "--out", str(out)])
    assert "\r" not in done.stderr and done.stderr.endswith("\n")
    with open(out / "curve.csv", newline="") as fh:
        n_iso = sum(row["stage"] == "iso" for row in csv.DictReader(fh))
    iso = [line for line in done.stderr.splitlines() if line.startswith("iso: ")]
    assert n_iso > 1 and iso[0].startswith("iso: 0incr")
    assert re.match(rf"iso: {n_iso}incr \[.*p = 100\.0% of 5\.85e\+06 N/m\]$", iso[-1]), iso
    shear = [line for line in done.stderr.splitlines() if line.startswith("shear: ")]
    assert shear[-1].startswith("shear: 100%") and " 4/4 " in shear[-1]


def test_quiet_prints_nothing_on_success(tmp_path):
    """-q on a run that starts Warp (the DEM backend): not even Warp's banner or warnings."""
    done = run(["homogenization.biaxial", "--backend", "dem", "--threads", "1", "--eps-max", "0.001", "--increment",
                "5e-4", "--orientations", "4", "-q", "--out", str(tmp_path / "run")])
    assert done.stdout == "" and done.stderr == ""


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_on_a_terminal_redraws_in_place():
    stream = Terminal()
    with cli.progress_bar(total=3, desc="stage", file=stream) as bar:
        bar.update(3)
    assert "\r" in stream.getvalue()


def test_a_bar_in_a_log_writes_a_line_at_the_start_and_at_the_end_only_when_fast():
    stream = io.StringIO()
    for _ in cli.progress_bar(range(10_000), desc="stage", unit="incr", file=stream, leave=False):
        pass
    lines = stream.getvalue().splitlines(keepends=True)
    assert len(lines) == 2 and all(line.endswith("\n") and "\r" not in line for line in lines)
    assert lines[0].startswith("stage:   0%") and lines[1].startswith("stage: 100%") and "10000/10000" in lines[1]
