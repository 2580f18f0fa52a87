"""Shared fixtures: Warp devices to test on (cpu, plus cuda:0 where Warp sees a GPU); each test starts
with the commands' output verbosity at its default (a command's ``main`` called directly with -q
leaves the process quiet, as ``run_main`` would not). The modules with the longest tests run first
(``LONG_FIRST``), so that with ``make test``'s work stealing no long test is left alone at the end. The checks of
the compiled steps on other CPUs (``other_cpus``) run once per session, whichever worker asks first."""

import fcntl
import json
import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


def _warp_devices() -> list[str]:
    try:
        import warp as wp
    except ImportError:
        return ["cpu"]
    wp.config.quiet = True
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=_warp_devices())
def device(request) -> str:
    """Warp device name to run kernels on."""
    return request.param


@pytest.fixture(autouse=True)
def _default_verbosity():
    """Restore -q's process-wide effect (``warp_hcell.core.cli._OUTPUT``) after each test."""
    from warp_hcell.core import cli  # noqa: PLC0415
    yield
    cli._OUTPUT.quiet = False


@pytest.fixture(scope="session")
def other_cpus(request, tmp_path_factory):
    """``other_cpus.Runs`` of the checks that this session's tests marked ``other_cpus`` name: the first test process
    that asks runs them (one process per CPU, every check at once); the others (pytest-xdist workers) wait for it
    and read its results."""
    import other_cpus as runs  # noqa: PLC0415 (the checks' states: built only where asked)
    from homogenization.ann import default_model_path  # noqa: PLC0415

    checks = sorted({mark.args[0] for item in request.session.items for mark in item.iter_markers("other_cpus")})
    checks = [c for c in checks if default_model_path(3).is_file() or not runs.CHECKS[c].shipped_3d]
    root = tmp_path_factory.getbasetemp()
    root = root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root  # shared by the workers of this session
    directory, done = root / "other_cpus", root / "other_cpus.json"
    with open(root / "other_cpus.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            done.write_text(json.dumps(runs.run_other_cpus(directory, checks)))
            if os.environ.get(runs.COMPILED_SIGNAL):
                Path(os.environ[runs.COMPILED_SIGNAL]).touch()
    return runs.Runs(directory, json.loads(done.read_text()))


LONG_FIRST = ("test_training_equilibrium3d.py", "test_homogenization_certificate_hybrid.py",
              "test_calibration_known_truth.py", "test_ann_control_diagnosis.py",
              "test_homogenization_active_rounds.py", "test_homogenization_active.py", "test_homogenization_sweep.py",
              "test_warp_hcell_generate.py", "test_training_inference.py", "test_cell_contract_conformance.py")
"""Test files whose tests take longest (tens of seconds each): collected first, in this order, each file's
tests together and in their own order (module fixtures are built once per worker as before)."""


def pytest_collection_modifyitems(config, items):
    """Move the tests of ``LONG_FIRST`` to the front; the order of the rest is kept."""
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keeps its order
