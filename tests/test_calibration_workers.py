"""hmodel calibrate --workers: the forward runs' parameter sets (or, fewer sets than workers, the tests) shared among
processes give the same curves and chain, bit for bit, as one process (a set's curves do not depend on its
population); refused in one line off the analytical backend."""

import json

import h5py
import numpy as np

from homogenization.calibration import bayes
from homogenization.calibration.data import read_test
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

FAST = ["--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none",
        "--resolution", "off", "-q"]


def _calibrate(tmp_path, workers: int):
    folder = tmp_path / f"w{workers}"
    folder.mkdir()
    drained, undrained = folder / "drained.csv", folder / "undrained.csv"
    drained.write_text("# test = drained\n# p0 = 2e5\neps1,q\n0.004,1.2e5\n0.008,1.6e5\n0.012,1.8e5\n")
    undrained.write_text("# test = undrained\n# p0 = 2e5\neps1,q\n0.004,1.0e5\n0.008,1.3e5\n0.012,1.4e5\n")
    out = folder / "cal"
    assert run_main(calibrate.main, ["--data", str(drained), "--data", str(undrained), "--params", "phi_g,alpha0",
                                     "--critical-state", "--walkers", "6", "--steps", "2", "--start", "prior",
                                     "--workers", str(workers), *FAST, "--out", str(out)]) == 0
    with h5py.File(out / "chain.h5", "r") as fh:
        chain = {name: np.array(fh["mcmc"][name]) for name in ("chain", "log_prob")}
    run = json.loads((out / "run.json").read_text())
    return chain, json.loads((out / "posterior.json").read_text()), run


def test_two_workers_give_one_process_chain_bit_for_bit(tmp_path):
    one, posterior_one, run_one = _calibrate(tmp_path, 1)
    two, posterior_two, run_two = _calibrate(tmp_path, 2)
    assert np.isfinite(one["log_prob"]).any()
    for name in one:
        assert np.array_equal(one[name], two[name]), name
    assert posterior_one == posterior_two
    counts = ("evaluations", "failed", "fallbacks", "jumps")
    assert [run_one["forward_model"][k] for k in counts] == [run_two["forward_model"][k] for k in counts]
    start_one, start_two = (run["start"]["forward_counts"] for run in (run_one, run_two))
    assert [start_one[k] for k in counts if k != "failed"] == [start_two[k] for k in counts if k != "failed"]
    assert start_one["fallbacks"] > 0  # the start's prior draws' (48 sets; the sampler's 18 have none)
    # numpy operations that raised a flag: each worker's share counts its own, so two shares count more
    assert 0 < start_one["floating_point_errors"] < start_two["floating_point_errors"]


def test_workers_off_the_analytical_backend_exit_2(tmp_path, capsys):
    data = tmp_path / "d.csv"
    data.write_text("# test = drained\n# p0 = 2e5\neps1,q\n0.004,1.2e5\n0.008,1.6e5\n")
    out = tmp_path / "x"
    assert run_main(calibrate.main, ["--data", str(data), "--params", "phi_g", "--backend", "dem", "--workers", "2",
                                     "--walkers", "4", "--steps", "2", *FAST, "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "--workers 2 shares the analytical backend's forward runs" in lines[0], lines
    assert not out.exists()


def test_a_single_set_shares_its_tests_among_workers_with_the_same_bits(tmp_path):
    """Fewer sets than workers (a least-squares step): each test runs in its own process, the same curves."""
    paths = []
    for name, q in (("drained", "1.2e5,1.6e5"), ("undrained", "1.0e5,1.3e5")):
        path = tmp_path / f"{name}.csv"
        a, b = q.split(",")
        path.write_text(f"# test = {name}\n# p0 = 2e5\neps1,q\n0.004,{a}\n0.008,{b}\n")
        paths.append(path)
    args = calibrate.build_parser().parse_args(["--data", str(paths[0]), "--params", "phi_g,alpha0", "--critical-state",
                                                *FAST, "--out", str(tmp_path / "o")])
    tests, settings = [read_test(p) for p in paths], calibrate.forward_settings(args, 2)
    prior = bayes.make_prior(["phi_g", "alpha0"], dim=2)
    one, two = (bayes.Posterior(tests, prior, settings, 0.02, workers=w) for w in (1, 2))
    try:
        for values in (np.array([[24.0, 50.0]]), np.array([[24.0, 50.0], [30.0, 60.0], [20.0, 47.0]])):
            a, b = one.curves(values), two.curves(values)
            for k in range(2):
                for name in a[k]:
                    assert np.array_equal(a[k][name], b[k][name], equal_nan=True), (values.shape, k, name)
        assert two._pool is not None and one._pool is None
    finally:
        two.close()
