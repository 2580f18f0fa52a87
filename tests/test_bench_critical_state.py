"""studies/bench_critical_state.py measures candidate cell rules against the calibration's forward
model: its plain path must be that forward model bit for bit, and a rule that never fires must leave it
unchanged, or its tables compare unlike things."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(ROOT / "studies"))
    try:
        spec = importlib.util.spec_from_file_location("_bench_critical_state", ROOT / "studies" / "bench_critical_state.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(ROOT / "studies"))


def _short_test(bench, eps_max: float = 0.03):
    test = bench.read_test(bench.DATA / "cid_50kpa.csv")
    keep = test.eps1 <= eps_max
    return replace(test, eps1=test.eps1[keep], observed={k: v[keep] for k, v in test.observed.items()})


def _params(bench, n: int = 1) -> dict[str, np.ndarray]:
    return {k: np.full(n, v) for k, v in bench.optimum("50+200").items()}


def test_plain_path_is_the_forward_model(bench):
    test = _short_test(bench)
    ours, counts = bench.simulate(test, _params(bench), None, None)
    theirs = bench.forward.simulate(test, _params(bench), bench.SETTINGS)
    for channel in ("q", "p", "eps_v"):
        np.testing.assert_array_equal(ours.channel(channel), theirs.channel(channel))
    assert counts.tolist() == [0]


def test_rules_that_do_not_fire_leave_the_cell_unchanged(bench):
    test = _short_test(bench)
    plain, _ = bench.simulate(test, _params(bench), None, None)
    # no renewal at lambda = 0; no plane opens to 89 deg or closes to 40 deg within 3 % of axial strain
    for candidate, value in (("renewal", 0.0), ("freeze", 89.0), ("lock", 40.0)):
        curves, counts = bench.simulate(test, _params(bench), candidate, np.array([value]))
        np.testing.assert_array_equal(curves.q, plain.q, err_msg=candidate)
        np.testing.assert_array_equal(curves.eps_v, plain.eps_v, err_msg=candidate)
        assert counts.tolist() == [0], candidate


def test_renewal_fires_as_often_as_its_rate_says(bench):
    """Each cell is renewed floor(lambda s + phase) - floor(phase) times, s its accumulated distortion:
    at lambda = 20 and 3 % of axial strain, every point renews some of its cells and its curve changes."""
    test = _short_test(bench)
    plain, _ = bench.simulate(test, _params(bench), None, None)
    curves, counts = bench.simulate(test, _params(bench), "renewal", np.array([20.0]))
    assert counts[0] > 0
    assert not np.array_equal(curves.q, plain.q)
