"""Shared fixtures: Warp devices to test on (cpu, plus cuda:0 where Warp sees a GPU); each test starts
with the commands' output verbosity at its default (a command's ``main`` called directly with -q
leaves the process quiet, as ``run_main`` would not)."""

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
