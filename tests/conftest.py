"""Shared fixtures: Warp devices to test on (cpu, plus cuda:0 where Warp sees a GPU); each test starts
with the commands' output verbosity at its default (a command's ``main`` called directly with -q
leaves the process quiet, as ``run_main`` would not). The modules with the longest tests run first
(``LONG_FIRST``), so that with ``make test``'s work stealing no long test is left alone at the end."""

import os

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
