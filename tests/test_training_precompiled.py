"""The planar step loaded without numba (``training.precompiled``) against numba's kernel.

The precompiled step must give every output of numba's ``training.fast_increment.step`` bit for bit, build its
object where none is cached, load it in a fresh process that never imports numba, key it on what changes the
machine code, and fall back to numba's kernel (the same bits) where it cannot be used.
"""

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from other_cpus import planar_loaded, spatial_loaded
from training import precompiled
from training.inference import FastAdvance, FastIncrement

ROOT = Path(__file__).resolve().parents[1]
MAPPED = sys.platform.startswith("linux") and platform.machine() == "x86_64"
"""Whether ``training.precompiled.map_object`` loads the step here (else llvmlite's engine does)."""


@pytest.fixture(scope="module")
def loaded():
    return planar_loaded()


def _run(fast: FastAdvance, state, d, steps: int = 3) -> list[FastIncrement]:
    """``steps`` increments from ``state``, each from the last one's new state (copies kept)."""
    out = []
    for _ in range(steps):
        inc = fast(*state, d)
        out.append(FastIncrement(*(np.array(a) for a in inc)))
        state = (inc.cell_size, inc.free_position, inc.shear_force)
    return out


@pytest.fixture(scope="module")
def cache(loaded, tmp_path_factory):
    """(cache folder, its FastAdvance, its first three increments): the step built where nothing was cached."""
    folder = tmp_path_factory.mktemp("numba_cache")
    cell, state, d = loaded
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("NUMBA_CACHE_DIR", str(folder))
        patch.setattr(precompiled, "_LOADED", {})
        fast = FastAdvance(cell.net)
        return folder, fast, _run(fast, state, d)


def _assert_same(a: list[FastIncrement], b: list[FastIncrement]) -> None:
    for k, (x, y) in enumerate(zip(a, b)):
        for name in FastIncrement._fields:
            assert getattr(x, name).tobytes() == getattr(y, name).tobytes(), f"increment {k}: {name}"


def test_the_precompiled_step_gives_numbas_bits_and_builds_where_nothing_is_cached(loaded, cache, monkeypatch):
    folder, built, first = cache
    assert built.step_path == "precompiled", built.precompiled_reason
    assert len(list((folder / "precompiled").glob("step-*.bin"))) == 1
    cell, state, d = loaded
    numba_path = FastAdvance(cell.net, precompiled=False)
    _assert_same(first, _run(numba_path, state, d))
    assert numba_path.step_path == "numba"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(folder))
    monkeypatch.setattr(precompiled, "_LOADED", {})  # as a new process: the object is read from its file
    again = FastAdvance(cell.net)
    _assert_same(first, _run(again, state, d))
    assert again.step_path == "precompiled", again.precompiled_reason
    assert (again.precompiled_loader == "mapped") == MAPPED, again.precompiled_loader


def test_llvmlites_engine_loads_the_same_bits_where_the_object_cannot_be_mapped(loaded, cache, monkeypatch):
    folder, _, first = cache
    cell, state, d = loaded

    def refuse(*args):
        raise ValueError("refused by the test")

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(folder))
    monkeypatch.setattr(precompiled, "_LOADED", {})
    monkeypatch.setattr(precompiled, "map_object", refuse)
    fast = FastAdvance(cell.net)
    _assert_same(first, _run(fast, state, d))
    assert fast.step_path == "precompiled" and fast.precompiled_loader == "llvmlite: refused by the test"


@pytest.mark.skipif(not MAPPED, reason="the object is mapped by this module on x86-64 Linux only")
def test_an_object_that_cannot_be_mapped_is_refused_and_leaves_nothing_mapped(cache):
    (built,) = (cache[0] / "precompiled").glob("step-*.bin")
    name, code, symbols = precompiled.PrecompiledStep._read(built)
    mapped = len(precompiled._MAPPINGS)
    with pytest.raises(ValueError, match="not an x86-64 ELF"):
        precompiled.map_object(b"\x7fELF" + code[4:16] + b"\x02\x00" + code[18:], name, {})  # an executable
    undefined = sorted(precompiled._undefined_symbols(code))
    with pytest.raises(ValueError, match="symbol not found"):
        precompiled.map_object(code, name, {s: 1 for s in symbols if s != undefined[0]})
    with pytest.raises(ValueError, match="no function"):
        precompiled.map_object(code, "absent", {s: 1 for s in symbols})
    assert len(precompiled._MAPPINGS) == mapped


def test_a_fresh_process_loads_the_step_without_importing_numba(loaded, cache, tmp_path, monkeypatch):
    folder, _, increments = cache
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(folder))
    _, state, d = loaded
    expected = increments[0]
    np.savez(tmp_path / "in.npz", *state, d)
    script = f"""
import json, sys
import numpy as np
from homogenization.ann.cell import AnnCell
from training.inference import FastAdvance
from warp_hcell.core.parameters import ContactLaw
data = np.load({str(tmp_path / 'in.npz')!r})
args = [data[f"arr_{{k}}"] for k in range(4)]
fast = FastAdvance(AnnCell(ContactLaw(), 0.5).net)
inc = fast(*args)
np.savez({str(tmp_path / 'out.npz')!r}, *inc)
print(json.dumps({{"numba": sorted(m for m in sys.modules if m == "numba" or m.startswith("numba.")),
                  "llvmlite": "llvmlite" in sys.modules, "path": fast.step_path, "reason": fast.precompiled_reason}}))
"""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["path"] == "precompiled", report["reason"]
    # only numba's C extension modules (its runtime's helpers), none of its Python; no llvmlite where mapped
    assert set(report["numba"]) <= {"numba._helperlib", "numba.core.runtime._nrt_python"}, report["numba"]
    assert report["llvmlite"] == (not MAPPED), report
    out = np.load(tmp_path / "out.npz")
    for k, name in enumerate(FastIncrement._fields):
        assert out[f"arr_{k}"].tobytes() == getattr(expected, name).tobytes(), name


def test_the_key_follows_the_argument_types_numbas_settings_and_the_sources(loaded, monkeypatch):
    cell, state, d = loaded
    fast = FastAdvance(cell.net)
    fast(*state, d)
    args = fast._local.work, fast._tables  # the fixed parts of a call: tables and scratch
    call = (np.zeros((2, 3)), np.zeros((4, 3)), np.zeros((15, 3)), np.zeros((3, 2)), *args[1], args[0].before,
            args[0].layers, fast._result(3), args[0].counts)
    key, fields = precompiled.step_key(call)
    assert key == precompiled.step_key(call)[0]
    assert "training/fast_increment.py" in fields["sources"]
    other_dtype = (np.zeros((2, 3), dtype=np.float32), *call[1:])
    assert precompiled.step_key(other_dtype)[0] != key
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/elsewhere")  # where the object is kept is not what it is
    assert precompiled.step_key(call)[0] == key
    monkeypatch.setenv("NUMBA_CPU_NAME", "generic")
    assert precompiled.step_key(call)[0] != key
    monkeypatch.delenv("NUMBA_CPU_NAME")
    precompiled._machine.cache_clear()
    monkeypatch.setattr(precompiled, "_host_cpu", lambda: {"model name": "another CPU"})
    assert precompiled.step_key(call)[0] != key
    monkeypatch.undo()
    precompiled._machine.cache_clear()
    assert precompiled.step_key(call)[0] == key
    monkeypatch.setattr(precompiled, "_SOURCES", precompiled._SOURCES[:-1])
    precompiled._machine.cache_clear()  # the sources are read once per process: read again here, and after the test
    try:
        assert precompiled.step_key(call)[0] != key
    finally:
        monkeypatch.undo()
        precompiled._machine.cache_clear()


def test_where_the_step_cannot_be_precompiled_numbas_kernel_gives_the_same_bits(loaded, tmp_path, monkeypatch):
    cell, state, d = loaded
    expected = _run(FastAdvance(cell.net, precompiled=False), state, d)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(precompiled, "_offsets_agree", lambda: False)
    fast = FastAdvance(cell.net)
    _assert_same(expected, _run(fast, state, d))
    assert fast.step_path == "numba" and "layout" in fast.precompiled_reason


def test_a_damaged_cache_file_is_built_again(loaded, cache, tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    cell, state, d = loaded
    expected = cache[2]
    (built,) = (cache[0] / "precompiled").glob("step-*.bin")
    path = tmp_path / "precompiled" / built.name
    path.parent.mkdir()
    path.write_bytes(b"\x05\x00\x00\x00\x00\x00\x00\x00{oops")
    monkeypatch.setattr(precompiled, "_LOADED", {})
    fast = FastAdvance(cell.net)
    _assert_same(expected, _run(fast, state, d))
    assert fast.step_path == "precompiled", fast.precompiled_reason
    assert path.read_bytes()[:8] != b"\x05\x00\x00\x00\x00\x00\x00\x00"


@pytest.mark.parametrize("layout_agrees", [True, False])
def test_a_run_records_which_code_ran_its_planar_step(tmp_path, monkeypatch, layout_agrees):
    import h5py  # noqa: PLC0415

    from homogenization.cli import biaxial  # noqa: PLC0415
    from warp_hcell.core.cli import run_main  # noqa: PLC0415

    if not layout_agrees:
        monkeypatch.setattr(precompiled, "_offsets_agree", lambda: False)
    out = tmp_path / "run"
    assert run_main(biaxial.main, ["--backend", "ann", "--orientations", "6", "--eps-max", "5e-4", "--increment", "1e-4",
                                   "--p0", "2e5", "-q", "--out", str(out)]) == 0
    with h5py.File(out / "run.h5") as run:
        record = json.loads(run.attrs["parameters"])["ann_model"]["compiled_step"]
    if layout_agrees:
        assert record["path"] == "precompiled" and (record["loader"] == "mapped") == MAPPED, record
    else:
        assert record["path"] == "numba" and "layout" in record["reason"]


def test_the_spatial_step_precompiled_gives_numbas_bits(tmp_path, monkeypatch):
    """The spatial fused step (``training.fast_step3d.step3d``) is built, keyed apart from the planar one and gives
    numba's bits."""
    cell, state, d = spatial_loaded()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(precompiled, "_LOADED", {})
    built = FastAdvance(cell.net)
    first = _run(built, state, d)
    assert built.step_path == "precompiled", built.precompiled_reason
    assert len(list((tmp_path / "precompiled").glob("step-*.bin"))) == 1
    args = (np.zeros((3, 2)), 1.0)
    assert precompiled.step_key(args, "training.fast_step3d:step3d")[0] != precompiled.step_key(args)[0]
    numba_path = FastAdvance(cell.net, precompiled=False)
    _assert_same(first, _run(numba_path, state, d))
    assert numba_path.step_path == "numba"
