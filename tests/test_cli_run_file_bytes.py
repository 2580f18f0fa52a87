"""Two runs of the same inputs write byte-identical run.h5 files, apart from the one attribute
documented as the invocation's (``command``, homogenization.output.io)."""

from __future__ import annotations

import time

import h5py

from homogenization.cli import biaxial
from homogenization.output import io
from warp_hcell.core import cli

TINY = ["--alpha0", "55", "--eps-max", "0.002", "--increment", "5e-4", "--orientations", "12", "-q"]


def run_file(out) -> bytes:
    assert cli.run_main(biaxial.main, [*TINY, "--overwrite", "--out", str(out)]) == 0
    return (out / io.RUN_FILE).read_bytes()


def test_the_same_command_twice_gives_the_same_bytes(tmp_path):
    first = run_file(tmp_path / "run")
    time.sleep(1.1)  # HDF5 object timestamps have a resolution of one second
    assert run_file(tmp_path / "run") == first


def test_runs_into_two_folders_differ_in_the_command_attribute_only(tmp_path):
    a = run_file(tmp_path / "run_a")
    time.sleep(1.1)
    b = run_file(tmp_path / "run_b")
    commands = []
    for out in ("run_a", "run_b"):
        with h5py.File(tmp_path / out / io.RUN_FILE) as f:
            commands.append(f.attrs["command"].encode())
    assert a != b and commands[0] != commands[1] and len(commands[0]) == len(commands[1])
    assert a.count(commands[0]) == 1 and a.replace(commands[0], commands[1]) == b


def test_no_object_carries_a_timestamp_and_the_creation_order_is_kept(tmp_path):
    run_file(tmp_path / "run")
    with h5py.File(tmp_path / "run" / io.RUN_FILE) as f:
        names = ["/"]
        f.visit(names.append)
        assert len(names) > 20
        assert {h5py.h5g.get_objinfo(f.id, name.encode()).mtime for name in names} == {0}
        assert list(f.attrs)[:3] == ["format", "backend", "alpha0_deg"]
        assert list(f) == ["history", "diagnostics", "orientations", "snapshots", "final_state"]
