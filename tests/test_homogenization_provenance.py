"""What run.h5 records about its making: command line, package version, DEM settings, ANN
model path and sha256; and the settings biaxial resolves (contact law, iso increment)."""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import subprocess
import sys
from dataclasses import asdict
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from homogenization.cli import biaxial
from homogenization.output import io
from warp_hcell.core.cli import run_main
from warp_hcell.core import provenance
from warp_hcell.core.parameters import DemSettings
from warp_hcell.core.provenance import command_line, file_sha256

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--alpha0", "55", "--eps-max", "0.005", "--increment", "5e-4", "--orientations", "12", "-q"]


def test_file_sha256_matches_hashlib(tmp_path):
    path = tmp_path / "blob"
    path.write_bytes(os.urandom(3 << 20))
    assert file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_ann_run_records_the_shipped_model_and_its_hash(tmp_path):
    from homogenization.ann import default_model_path

    argv = ["--backend", "analytical,ann", *TINY, "--out", str(tmp_path / "r")]
    assert run_main(biaxial.main, argv) == 0
    stored = io.read_run(tmp_path / "r" / "ann" / "run.h5")
    model = stored.attrs["parameters"]["ann_model"]
    assert model["path"] == str(default_model_path().resolve())
    assert model["sha256"] == hashlib.sha256(default_model_path().read_bytes()).hexdigest()
    assert stored.attrs["command"] == "hmodel biaxial " + " ".join(argv)
    assert stored.attrs["code_version"] == metadata.version("meso-hmodel")
    assert "ann_model" not in io.read_run(tmp_path / "r" / "analytical" / "run.h5").attrs["parameters"]


def test_dem_run_records_its_settings_and_threads(tmp_path):
    assert run_main(biaxial.main, ["--backend", "dem", "--threads", "1", *TINY, "--out", str(tmp_path / "d")]) == 0
    parameters = io.read_run(tmp_path / "d" / "run.h5").attrs["parameters"]
    assert parameters["dem_settings"] == asdict(DemSettings())
    assert parameters["dem_threads"] == 1


def test_contact_law_and_radius_flags_reach_the_cells(tmp_path):
    out = tmp_path / "law"
    argv = [*TINY, "--kn", "1e8", "--kt", "8e7", "--phi", "20", "--radius", "0.25", "--out", str(out)]
    assert run_main(biaxial.main, argv) == 0
    stored = io.read_run(out / "run.h5")
    assert stored.attrs["parameters"]["contact_law"] == {"kn": 1e8, "kt_over_kn": 0.8, "phi_g_deg": 20.0}
    assert stored.attrs["parameters"]["radius"] == 0.25
    default = tmp_path / "default"
    assert run_main(biaxial.main, [*TINY, "--out", str(default)]) == 0
    reference = io.read_run(default / "run.h5")
    # V0 scales with r^2; the softer contacts need more isotropic strain to reach p0
    assert stored.record.V0 == pytest.approx(0.25 * reference.record.V0, rel=1e-12)
    iso = stored.record.stage == "iso"
    assert stored.record.eps11[iso][-1] > 1.5 * reference.record.eps11[reference.record.stage == "iso"][-1]


def test_iso_increment_follows_a_coarse_shear_increment(tmp_path):
    out = tmp_path / "coarse"
    assert run_main(biaxial.main, ["--increment", "1e-4", "--eps-max", "0.002", "--orientations", "12", "-q",
                                   "--out", str(out)]) == 0
    stored = io.read_run(out / "run.h5")
    assert stored.attrs["parameters"]["iso_increment"] == pytest.approx(5e-5)
    iso = stored.record.stage == "iso"
    steps = np.diff(stored.record.eps11[iso])
    assert np.allclose(steps[:-1], 5e-5) and int(iso.sum()) < 1000  # 5,200 at the old 5e-6


def test_command_line_names_the_module_of_a_python_m_run():
    code = "from warp_hcell.core.provenance import command_line; print(command_line())"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code, "--flag", "a b"], capture_output=True, text=True, env=env)
    assert done.stdout.strip() == "-c --flag 'a b'"
    assert command_line()  # the pytest process has one


def test_git_revision_marks_a_tree_with_changed_tracked_files_dirty(tmp_path):
    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), *args], capture_output=True, text=True, check=True).stdout

    shutil.copy(provenance.__file__, tmp_path / "provenance.py")
    git("init", "-q")
    git("add", "provenance.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    spec = importlib.util.spec_from_file_location("provenance_copy", tmp_path / "provenance.py")
    copy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(copy)
    head = git("rev-parse", "HEAD").strip()
    (tmp_path / "untracked.txt").write_text("not part of the tree\n")
    assert copy.git_revision() == head
    with open(tmp_path / "provenance.py", "a") as fh:
        fh.write("# changed\n")
    assert copy.git_revision() == head + "-dirty"


def test_cpu_model_reads_the_systems_processor_name_and_falls_back_without_one(tmp_path):
    listing = tmp_path / "cpuinfo"
    listing.write_text("processor\t: 0\nvendor_id\t: Some\nmodel name\t: Example CPU 9000 @ 3.0GHz\n\n"
                       "processor\t: 1\nmodel name\t: Another\n")
    assert provenance.cpu_model(listing) == "Example CPU 9000 @ 3.0GHz"
    listing.write_text("processor\t: 0\nCPU implementer\t: 0x41\n")
    fallback = provenance.cpu_model(listing)
    assert fallback and fallback == provenance.cpu_model(tmp_path / "missing")
    assert provenance.provenance()["cpu"] == provenance.cpu_model()
