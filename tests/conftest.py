"""Shared fixtures: Warp devices to test on (cpu, plus cuda:0 where Warp sees a GPU)."""

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
