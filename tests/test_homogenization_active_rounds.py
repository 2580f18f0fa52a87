"""The rules of the active-learning rounds (homogenization.learning.active): where a failing test's states are
taken (from the ANN's point of departure on, a test the ANN cannot follow included), when the rounds
stop for want of progress (one line saying which test, which rounds, what they tried), and the
database's size budget (a round adds only what fits; none once it is spent)."""

import dataclasses
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from homogenization.learning import active, certificate
from homogenization.ann.records import Certificate, Round, TestResult
from homogenization.learning.settings import ActiveSettings, CertificateSettings
from test_homogenization_active import SHORT, TRAIN_CONFIG, tiny, tiny_built  # noqa: F401 (the fixtures)
from training import train as training_train
from warp_hcell.core.parameters import DatabaseSettings
from warp_hcell.core.provenance import file_sha256
from warp_hcell.database import generate
from warp_hcell.database import format as database
from warp_hcell.database.format import CHUNK_BYTES, sizes
from warp_hcell.mesostructures.builders import mesostructure_arg

CELL_3D = "hcell3d-fines:alpha0=53,ratio=0.74,n=0.06,t2=0.04"
"""A ten-sphere cell with a free fine sphere off the pore centre (benchmarks/bench_pipeline3d.py's)."""
SMALL_3D = DatabaseSettings(samples=3000)
"""The generator's exploration, 3,000 samples: 8 s on one core."""


def _record(stage, p, q):
    """The parts of a ``driver.Record`` that ``certificate.departure`` reads."""
    return SimpleNamespace(stage=np.array(stage), programme=[SimpleNamespace(label="iso")], p=np.array(p, float),
                           q=np.array(q, float))


def test_departure_is_the_first_shear_increment_beyond_the_target():
    dem = _record(["iso", "iso", "shear", "shear", "shear", "shear"], [1, 2, 3, 4, 5, 6], [0, 0, 1, 2, 3, 4])
    ann = _record(["iso", "shear", "shear", "shear", "shear"], [1, 3, 4.05, 5.2, 9], [0, 1, 2, 3, 4])
    # the ANN's isotropic stage is one increment shorter: rows are aligned over the shear stages
    assert certificate.departure(ann, dem, scale=10.0, target=0.01) == 4  # |5.2 - 5| = 0.2 > 0.1 at DEM row 4
    assert certificate.departure(ann, dem, scale=10.0, target=0.25) == 5  # |9 - 6| = 3 > 2.5
    assert certificate.departure(ann, dem, scale=10.0, target=1.0) is None


def _certificate(*tests, target=0.02):
    """A certificate of target ``target`` whose tests are these rows (their other fields placeholders)."""
    rows = tuple(TestResult.from_dict({"kind": "drained", "sense": "compression", "p0": 2e5, "scale": 2e5,
                                       "n_increments": 100, **t}) for t in tests)
    worst = max(rows, key=lambda t: t.figure)
    return Certificate(target=target, worst=worst.figure, worst_test=worst.name, metric="", tests=rows, rollout=None,
                       coverage=None, dem_spread=None, settings={}, cell_parameters={}, model_sha256="", revision="",
                       seconds=0.0, within_target=False, below_minimum=[], verdict="failed", passed=False)


def test_failing_states_are_those_from_the_departure_on():
    increments = np.tile(np.arange(0, 100, 10), 2)  # two cells, a state every 10 increments
    states = {"cell_size": np.ones((20, 3)), "position": np.zeros((20, 11, 3)), "shear_force": np.zeros((20, 55, 3)),
              "cell": np.repeat([0, 1], 10), "increment": increments}
    cert = _certificate(
        {"name": "a", "dp": math.inf, "dq": math.inf, "departure": 60, "n_increments": 100},
        {"name": "b", "dp": 0.05, "dq": 0.0, "departure": 95, "n_increments": 100},
        {"name": "c", "dp": 0.01, "dq": 0.0, "n_increments": 100},  # passed: none of its states
        {"name": "d", "dp": 0.03, "dq": 0.0, "n_increments": 100})  # no departure recorded: every state
    dem_states = {name: dict(states) for name in "abcd"}
    picked, names = active.failing_states(cert, dem_states, margin=0.1)
    assert names == ["a", "b", "d"]
    assert picked["cell_size"].shape[0] == 2 * 5 + 2 * 1 + 20  # a: 50-90; b: 90; d: all
    picked, _ = active.failing_states(cert, dem_states, margin=1.0)
    assert picked["cell_size"].shape[0] == 3 * 20


def _entry(k, worst, not_followed=(), followed=0.0):
    return Round(round=k, samples_added=0, samples_total=0, worst=worst, worst_test="", passed=False, seconds=0.0,
                 not_followed=list(not_followed), followed=followed)


def test_progress_rule_and_stall():
    assert active.improved(_entry(1, math.inf, ["x"]), _entry(0, math.inf, ["x", "y"]))  # fewer not followed
    assert active.improved(_entry(1, math.inf, ["x"], 0.5), _entry(0, math.inf, ["x"], 0.3))  # followed further
    assert not active.improved(_entry(1, math.inf, ["x"], 0.31), _entry(0, math.inf, ["x"], 0.3))
    assert active.improved(_entry(1, 0.05), _entry(0, math.inf, ["x"]))  # every test followed
    assert not active.improved(_entry(1, math.inf, ["x"]), _entry(0, 0.5))
    assert active.improved(_entry(1, 0.08), _entry(0, 0.1)) and not active.improved(_entry(1, 0.095), _entry(0, 0.1))
    settings = ActiveSettings(stall_rounds=2)
    rounds = [_entry(0, 0.1), _entry(1, 0.05), _entry(2, 0.048), _entry(3, 0.06)]
    assert active.best_round(rounds).round == 1
    assert not active.stalled(rounds[:3], settings) and active.stalled(rounds, settings)
    # a record without the fields (written before them): an infinite worst counts as one test not followed
    old = Round(round=0, samples_added=0, samples_total=0, worst=math.inf, worst_test="", passed=False, seconds=0.0)
    assert active.progress(old) == (1, 0.0, math.inf)


def test_rounds_stop_where_every_failing_test_is_within_the_dems_own_reproducibility():
    def cert(*tests):
        return _certificate(*(dict(zip(("name", "dp", "dq", "dem_spread"), t)) for t in tests))

    within = cert(("drained", 0.01, 0.031, 0.0318), ("undrained", 0.003, 0.009, 0.007))
    line = active.unresolvable_line(within)
    assert line.startswith("active learning stops: every failing test") and "drained 3.100 % against 3.180 %" in line
    assert "undrained" not in line  # a passing test is no matter
    assert active.unresolvable_line(cert(("drained", 0.01, 0.031, 0.0318), ("other", 0.03, 0.0, 0.001))) is None
    assert active.unresolvable_line(cert(("drained", math.inf, math.inf, 0.0318))) is None  # not followed
    assert active.unresolvable_line(cert(("passing", 0.01, 0.0, 0.05))) is None
    no_spread = _certificate({"name": "drained", "dp": 0.01, "dq": 0.031})  # not measured
    assert active.unresolvable_line(no_spread) is None


@pytest.fixture(scope="module")
def model_3d(tmp_path_factory):
    """A poorly trained model of a tiny database of ``CELL_3D`` (3 epochs): it cannot follow drained tests."""
    folder = tmp_path_factory.mktemp("f3")
    meso = mesostructure_arg(CELL_3D).build()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "provenance", lambda: {"git_revision": "pinned"})
        generate.generate(meso, SMALL_3D, folder / "db.h5", seed=0, threads=1)
    model = folder / "m.pt"
    assert training_train.main(["--data", str(folder / "db.h5"), "--out", str(model), "--epochs", "3", "--hidden",
                                "16", "--no-rollout", "--threads", "1", "-q"]) == 0
    return folder / "db.h5", model


def test_a_drained_test_the_ann_cannot_follow_is_diagnosed_and_its_states_from_there_on_are_probed(model_3d):
    _, model = model_3d
    states = {}
    cert = certificate.certify(model, pressures=(2e5,), eps_max=0.01, spatial_rule=(5, 2), rollout=False,
                               dem_states=states, state_every=5)
    lost = [t for t in cert.tests if not math.isfinite(t.dp)]
    assert lost and math.isinf(cert.worst) and cert.verdict == "failed"
    for test in lost:  # one line: where, which cells (or none), the certificate's verdict
        assert test.kind == "drained" and "\n" not in test.error
        assert test.error.startswith("step 'shear', increment ") and "ANN diagnosis: " in test.error
        assert re.search(r"in \d+ of \d+ cells: \d+ \(n = |no cell of \d+ failed", test.error)
        assert "model not certified" in test.error
        shear = int(test.error.split("increment ")[1].split(":")[0])
        assert 0 < shear <= test.departure < test.n_increments  # the departure counts the isotropic stage too
    for test in cert.tests:
        assert (test.departure is not None) == (test.figure > cert.target)
    picked, names = active.failing_states(cert, states, margin=0.0)
    assert set(t.name for t in lost) <= set(names)
    first = {name: int(states[name]["increment"].min()) for name in names}
    kept = sum(int(np.count_nonzero(states[t.name]["increment"] >= t.departure)) for t in cert.tests
               if t.name in names)
    assert picked["cell_size"].shape[0] == kept < sum(states[name]["cell"].size for name in names)
    assert all(v == 0 for v in first.values())  # the certificate kept every test's states from its start


def test_rounds_without_progress_stop_with_one_line(tiny, monkeypatch, capsys):  # noqa: F811 (the fixture)
    db, model = tiny
    monkeypatch.setattr(active, "improved", lambda new, best: False)
    rounds, _ = active.learn(db, model, TRAIN_CONFIG, settings=ActiveSettings(rounds=3, samples_per_round=1000,
                                                                             stall_rounds=1, widen=False),
                             certify_settings=CertificateSettings(**SHORT, target=1e-9))
    assert [r.round for r in rounds] == [0, 1]
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("active learning stops")]
    assert len(lines) == 1
    line = lines[0]
    assert line.startswith("active learning stops: no progress in rounds 1-1 on round 0 (")
    assert f"worst test {rounds[1].worst_test!r}" in line and "tried 1000 samples on the DEM states of " in line
    assert "network 16" in line and "MB" in line
    # a second call finds the run finished: nothing added
    n = rounds[-1].samples_total
    again, _ = active.learn(db, model, TRAIN_CONFIG, settings=ActiveSettings(rounds=3, samples_per_round=1000,
                                                                             stall_rounds=1, widen=False),
                            certify_settings=CertificateSettings(**SHORT, target=1e-9))
    assert again[-1].samples_total == n and "(done before)" in capsys.readouterr().out


def test_the_database_budget_caps_a_round_and_then_stops_the_rounds(tiny, capsys):  # noqa: F811 (the fixture)
    db, model = tiny
    data, attrs = database.read_database(db)  # stored as the generator stores it: compressed
    database.write_database(db, data, attrs, database.read_attrs_of(db))
    active.train_model(db, model, TRAIN_CONFIG, [])
    size = db.stat().st_size
    budget = (size + 2000 * database.bytes_per_sample(db)) / 1e6
    rounds, _ = active.learn(db, model, TRAIN_CONFIG,
                          settings=ActiveSettings(rounds=6, samples_per_round=3000, max_database_mb=budget,
                                                  stall_rounds=5, widen=False),
                          certify_settings=CertificateSettings(**SHORT, target=1e-9))
    printed = capsys.readouterr().out
    # measured: round 1 adds 1,626 of its 3,000 (at 1.1x the 48-sample file's bytes per sample, its
    # probed states reserved); the grown file packs a sample in less, so rounds 2 and 3 add their 3,000,
    # then 761 fit and round 4 asks 3,000: the loop stops at 1.3 of 1.46 MB
    added, capped = [r.samples_added for r in rounds[1:]], [r.samples_capped for r in rounds[1:]]
    assert 3 <= len(rounds) <= 5 and 1000 <= added[0] <= 2000 / active.BUDGET_MARGIN and capped[0] > 0
    assert all(a + c == 3000 for a, c in zip(added, capped))
    assert f"{capped[0]} more did not fit the database budget" in printed
    assert printed.strip().splitlines()[-2].startswith("active learning stops: the database budget is spent (")
    assert printed.strip().splitlines()[-1].startswith(f"round rule: {len(rounds) - 1} round(s) trained")
    on_disk, raw = sizes(db)
    assert rounds[-1].database_mb == on_disk / 1e6 and rounds[-1].database_raw_mb == raw / 1e6
    assert on_disk <= 1e6 * budget
    with h5py.File(db) as f:
        stored = json.loads(f.attrs["active_learning"])
    assert [r["samples_capped"] for r in stored] == capped and [r["samples"] for r in stored] == added
    again, _ = active.learn(db, model, TRAIN_CONFIG,  # a second call: the budget is spent, no certificate again
                         settings=ActiveSettings(rounds=6, samples_per_round=3000, max_database_mb=budget,
                                                 stall_rounds=5, widen=False),
                         certify_settings=CertificateSettings(**SHORT, target=1e-9))
    assert again == rounds and "(done before)" in capsys.readouterr().out


def test_the_database_is_stored_compressed(model_3d):
    db, _ = model_3d
    on_disk, raw = sizes(db)
    assert raw > 3 * on_disk  # measured 4x on this cell
    with h5py.File(db) as f:
        springs = f["before/shear_force"]
        assert springs.compression == "gzip" and not springs.shuffle
        assert springs.chunks[1:] == springs.shape[1:] and springs.chunks[0] * springs[0].nbytes <= CHUNK_BYTES
        assert f["before/shear_force"].dtype == np.float64 and f["after/free_position"].dtype == np.float64
        assert f["after/normal_force"].dtype == np.float32 and "after/normal_force" in f.attrs["float32_datasets"]


def test_a_promotion_cut_short_is_completed(tmp_path, monkeypatch):
    """A kill between the renames of an accepted round's files leaves the new weights beside the old JSON; the next
    run completes the move (the weights, JSON and index one model's again)."""
    model = tmp_path / "ann.pt"
    for old, new in zip(active.model_files(model), active.model_files(active.candidate_path(model))):
        old.write_text("old " + old.name)
        new.write_text("new " + old.name)
    real = active.os.replace

    def killed_at_the_json(source, target):
        if Path(target).suffix == ".json":
            raise KeyboardInterrupt
        real(source, target)

    monkeypatch.setattr(active.os, "replace", killed_at_the_json)
    with pytest.raises(KeyboardInterrupt):
        active._promote(active.candidate_path(model), model)
    monkeypatch.setattr(active.os, "replace", real)
    assert model.read_text() == "new ann.pt" and model.with_suffix(".json").read_text() == "old ann.json"
    read = []

    def card_of(path):  # learn reads the model's JSON only after completing the move
        read.append(path.with_suffix(".json").read_text())
        raise LookupError

    monkeypatch.setattr(active, "read_card", card_of)
    with pytest.raises(LookupError):
        active.learn(tmp_path / "db.h5", model, TRAIN_CONFIG)
    assert read == ["new ann.json"] and not active.finish_promotion(model)
    assert [f.read_text() for f in active.model_files(model)] == [f"new {f.name}" for f in active.model_files(model)]
    assert not any(f.exists() for f in active.model_files(active.candidate_path(model)))


def test_bad_budget_settings_are_refused():
    for bad in ({"max_database_mb": 0.0}, {"stall_rounds": 0}, {"departure_margin": 1.5}):
        with pytest.raises(ValueError):
            ActiveSettings(**bad)



def test_the_round_rule_keeps_the_better_model():
    assert active.better(_entry(1, 0.05), _entry(0, 0.1)) and not active.better(_entry(1, 0.1), _entry(0, 0.1))
    assert not active.better(_entry(1, 0.2), _entry(0, 0.1))  # worse: rejected
    assert active.better(_entry(1, 0.5), _entry(0, math.inf, ["x"]))  # follows every test
    assert not active.better(_entry(1, math.inf, ["x"], 0.3), _entry(0, math.inf, ["x"], 0.3))
    rounds = [dataclasses.replace(_entry(k, worst), accepted=accepted)
              for k, (worst, accepted) in enumerate(((0.1, True), (0.05, True), (0.2, False), (0.06, False)))]
    assert active.kept_round(rounds).round == 1 and active.restarts(rounds) == 2
    assert active.rules_line(rounds).startswith("round rule: 3 round(s) trained, 1 accepted, 2 rejected (")
    assert "1 restarted with another training seed; kept: round 1 (worst 5.000 %)" in active.rules_line(rounds)


def test_a_round_that_makes_the_model_worse_is_rejected_and_the_kept_worst_never_rises(tiny, monkeypatch,  # noqa: F811
                                                                                        capsys):
    """The reduced pipeline end to end (48-sample database, 30 epochs, 6 orientations, one pressure):
    round 2's training is cut to one epoch, so its model is worse; the rule rejects it, keeps round
    1's model file and certificate, and round 3 restarts its training with the next seed."""
    db, model = tiny
    real = active.train_model

    def one_epoch_in_round_2(db_, model_, config, rounds, **kwargs):
        return real(db_, model_, dataclasses.replace(config, epochs=1) if len(rounds) == 2 else config, rounds, **kwargs)

    monkeypatch.setattr(active, "train_model", one_epoch_in_round_2)
    rounds, cert = active.learn(db, model, TRAIN_CONFIG, settings=ActiveSettings(rounds=3, samples_per_round=3000,
                                                                                stall_rounds=3, widen=False),
                                certify_settings=CertificateSettings(**SHORT, target=1e-9))
    printed = capsys.readouterr().out
    assert [r.round for r in rounds] == [0, 1, 2, 3] and rounds[1].accepted  # 6092 % -> 0.73 %
    assert rounds[2].worst > rounds[1].worst and rounds[2].accepted is False and rounds[2].epochs == 1
    assert "REJECTED: no better than round 1" in printed
    assert [r.train_seed for r in rounds] == [0, 0, 0, 1]  # round 3 restarts with the next seed
    kept = [active.kept_round(rounds[:k + 1]).worst for k in range(len(rounds))]
    assert all(b <= a for a, b in zip(kept, kept[1:])) and cert.worst == kept[-1] == min(r.worst for r in rounds)
    meta = json.loads(model.with_suffix(".json").read_text())  # the model on disk is the kept one
    assert meta["certificate"]["model_sha256"] == cert.model_sha256 == file_sha256(model)
    assert meta["certificate"]["worst"] == cert.worst and meta["history"]["epochs_run"] > 1
    assert not active.candidate_path(model).exists()
    assert printed.strip().splitlines()[-1].startswith(
        f"round rule: 3 round(s) trained, {3 - active.restarts(rounds)} accepted, {active.restarts(rounds)} rejected")


def test_rounds_fine_tune_the_kept_model_with_their_samples_at_their_share(tiny, monkeypatch):  # noqa: F811
    """make reproduce's rounds on the reduced pipeline: each round trains its candidate from the kept
    model's weights (--warm-start) with the rounds' samples at ``round_share`` of the loss, and the
    kept worst never rises."""
    db, model = tiny
    real, seen = active.train_model, []

    def recorded(db_, model_, config, rounds, **kwargs):
        seen.append(config)
        return real(db_, model_, config, rounds, **kwargs)

    monkeypatch.setattr(active, "train_model", recorded)
    config = dataclasses.replace(TRAIN_CONFIG, round_share=0.3)
    rounds, cert = active.learn(db, model, config, settings=ActiveSettings(rounds=2, samples_per_round=3000,
                                                                          stall_rounds=3, widen=False, warm_start=True),
                                certify_settings=CertificateSettings(**SHORT, target=1e-9))
    assert [r.round for r in rounds] == [0, 1, 2] and [r.warm_start for r in rounds[1:]] == [True, True]
    assert [(c.round_share, c.init_from) for c in seen] == [(0.3, str(model))] * 2
    kept = [active.kept_round(rounds[:k + 1]).worst for k in range(len(rounds))]
    assert all(b <= a for a, b in zip(kept, kept[1:])) and cert.worst == kept[-1]


def test_a_round_target_keeps_the_rounds_going_after_a_pass_and_picks_the_tests_above_it(monkeypatch):
    cert = dataclasses.replace(_certificate({"name": "a", "dp": 0.012, "dq": 0.0}, {"name": "b", "dp": 0.005, "dq": 0.0},
                                            {"name": "c", "dp": 0.001, "dq": 0.0}), verdict="passed", passed=True)
    monkeypatch.setattr(active, "verdict", lambda c: c.verdict)  # the figures alone decide, not the settings
    plain, strict = ActiveSettings(), ActiveSettings(round_target=0.004)
    assert active.aim(cert, plain) == 0.02 and active.aim(cert, strict) == 0.004
    assert active.aim(cert, ActiveSettings(round_target=0.05)) == 0.02  # never looser than the target
    assert not active.short_of_aim(cert, plain) and active.short_of_aim(cert, strict)
    assert not active.short_of_aim(dataclasses.replace(cert, verdict="weak"), strict)  # below the minimum: no rounds
    assert active.short_of_aim(dataclasses.replace(cert, verdict="failed"), plain)
    states = {"cell_size": np.ones((4, 2)), "position": np.zeros((4, 6, 2)), "shear_force": np.zeros((4, 9)),
              "cell": np.arange(4)}
    assert active.failing_states(cert, {n: dict(states) for n in "abc"})[1] == []  # none above the target
    picked, names = active.failing_states(cert, {n: dict(states) for n in "abc"}, threshold=active.aim(cert, strict))
    assert names == ["a", "b"] and picked["cell"].shape[0] == 8
    spread = _certificate({"name": "a", "dp": 0.006, "dq": 0.0, "dem_spread": 0.007})
    assert active.unresolvable_line(spread) is None  # nothing above the target
    assert "the aim 0.5 % is finer" in active.unresolvable_line(spread, 0.005)
    with pytest.raises(ValueError):
        ActiveSettings(round_target=0.0)


def test_rounds_go_on_past_a_passed_certificate_until_the_round_target(tiny, monkeypatch, capsys):  # noqa: F811
    """The reduced pipeline with the certificate's own target (2 %) read as the minimum's verdict: round 1 passes
    it and the rounds stop; asked again with a stricter round target the same run continues with round 2,
    probing the tests above that aim, while the certificate's target and verdict stay those of 2 %."""
    db, model = tiny
    monkeypatch.setattr(active, "verdict", lambda c: "passed" if c.worst <= c.target else "failed")
    measured = CertificateSettings(**SHORT)
    settings = ActiveSettings(rounds=3, samples_per_round=3000, stall_rounds=3, widen=False)
    rounds, cert = active.learn(db, model, TRAIN_CONFIG, settings=settings, certify_settings=measured)
    assert [r.round for r in rounds] == [0, 1] and cert.worst <= 0.02 < rounds[0].worst
    strict = dataclasses.replace(settings, round_target=cert.worst / 10)
    spent = sum(r.seconds for r in rounds)  # a resumed run's time budget counts the rounds of earlier processes
    again, _ = active.learn(db, model, TRAIN_CONFIG, settings=dataclasses.replace(strict, max_seconds=spent),
                            certify_settings=measured)
    assert [r.round for r in again] == [0, 1] and "active learning stops: budget spent" in capsys.readouterr().out
    rounds, after = active.learn(db, model, TRAIN_CONFIG, settings=strict, certify_settings=measured)
    assert [r.round for r in rounds] == [0, 1, 2, 3]  # the budget, not the pass, ended them
    assert after.target == 0.02 and after.worst <= cert.worst
    assert rounds[2].tests and all(cert.test(name).figure > strict.round_target for name in rounds[2].tests)
    assert "active round 2: +3000 samples" in capsys.readouterr().out


def test_certificates_of_one_process_run_their_dem_tests_once(tiny, monkeypatch):  # noqa: F811 (the fixture)
    """The rounds certify every candidate on the same tests: the DEM's side (records, states, reproducibility runs)
    runs once per process and settings, and the figures are those of a fresh run."""
    _, model = tiny
    certificate._LAST_REFERENCE.clear()
    made, real = [], certificate.make_cell_model
    monkeypatch.setattr(certificate, "make_cell_model", lambda kind, **kw: made.append(kind) or real(kind, **kw))
    first = certificate.certify(model, **SHORT)
    again = certificate.certify(model, **SHORT)
    assert made.count("dem") == 1 and again.tests == first.tests and again.dem_spread == first.dem_spread
    certificate.certify(model, **{**SHORT, "eps_max": 0.01})  # other tests: the DEM runs them
    assert made.count("dem") == 2
