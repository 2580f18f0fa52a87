"""Tests of warp_hcell.generate (and its jobs exploration / probing): the generic database of any
mesostructure, re-checked against the DEM, determinism, resume, the command line. About 2e3
samples per run."""

import errno
import json
import os
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from warp_hcell.database import exploration, format as database, generate, probing, shards
from warp_hcell import generate as generate_command
from warp_hcell.core import execution
from warp_hcell.dem.cell import DemCell
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.mesostructures.files import describe, description_sha256, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import StartCells, h_cell
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings, DemSettings
from warp_hcell.core.files import output_lock
from database_recheck import recheck_against_the_dem
from dask_cluster import free_port, local_cluster

DATA = Path(__file__).resolve().parents[1] / "warp_hcell" / "data"
STARTS = StartCells(n_alpha0=2, alpha0_focus_deg=(55.0,))
SMALL = DatabaseSettings(samples=2000, chunk_size=500,
                         precompression=(0.0, 1e-3, 1e-2), n_directions=8, sample_spacing=1e-2, leg_length=0.05,
                         leg_volumetric=0.05, leg_refinement=1)
LATERAL = load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")
FINE = replace(load_mesostructure(DATA / "h_cell_fine_grain.toml"), name="fine grain, no H-cell labels",
               pair_label=None, observables=(), parameters={})


@pytest.fixture(autouse=True)
def fixed_revision(monkeypatch):
    """Colleagues commit while tests run: pin the recorded provenance so files compare by bytes."""
    monkeypatch.setattr(generate, "provenance", lambda: {"git_revision": "pinned-for-tests"})


def run(tmp_path, name="db.h5", *, meso=LATERAL, settings=SMALL, **kwargs):
    out = tmp_path / name
    kwargs.setdefault("seed", 3)
    return generate.generate(meso, settings, out, **kwargs), out


@pytest.fixture(scope="module")
def h_db(tmp_path_factory):
    """A small H-cell database explored from H-cells at 30, 55 and 89 deg, cleaned."""
    out = tmp_path_factory.mktemp("h") / "h.h5"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "provenance", lambda: {"git_revision": "pinned-for-tests"})
        generate.generate(h_cell(), SMALL, out, seed=3, starts=STARTS.build(), clean=True)
    return database.read_database(out)


@pytest.fixture(scope="module")
def fine_db(tmp_path_factory):
    """A small database of the cell with a free fine grain in the pore (no H-cell observables used)."""
    out = tmp_path_factory.mktemp("fine") / "fine.h5"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "provenance", lambda: {"git_revision": "pinned-for-tests"})
        generate.generate(FINE, SMALL, out, seed=3)
    return database.read_database(out)


def test_leg_limits_follow_direction():
    directions = exploration.leg_directions(SMALL)
    arc = exploration.leg_arc(SMALL)
    steps = exploration.leg_steps(SMALL, directions, arc)
    np.testing.assert_allclose(arc, [5e-3, 1.5e-2, 2.5e-2, 3.5e-2, 4.5e-2])
    # psi = 45 deg (isotropic compression) is cut by the volumetric limit, psi = 135 deg is not
    assert steps[1] == 4  # 0.035 * sqrt(2) <= 0.05 < 0.045 * sqrt(2)
    assert steps[3] == arc.size


def test_generic_stop_rules():
    meso = h_cell()
    schema = meso.schema()
    law, tol = ContactLaw(), DemSettings().contact_tolerance
    n = 5
    position = np.repeat(meso.position[None], n, axis=0)
    arrays = {"position": position, "velocity": np.zeros_like(position), "shear_force": np.zeros((n, 15)),
              "cell_size": np.repeat(meso.cell_size[None], n, axis=0), "converged": np.array([1, 0, 1, 1, 1])}
    arrays["position"][2, 1, 0] = np.nan
    arrays["position"][3, 1, 0] -= 0.2 * 1.0  # grain 2 into grain 3: overlap 0.2 of r_2 + r_3
    eps = np.zeros((n, 2))
    eps[4] = (0.6, 0.0)
    free_run = np.array([0.0, 0.0, 0.0, 0.0, 0.05])
    masks = exploration.stop_masks(schema, arrays, eps, free_run, SMALL, law, tol)
    np.testing.assert_array_equal(masks["unconverged"], [0, 1, 0, 0, 0])
    np.testing.assert_array_equal(masks["non_finite"], [0, 0, 1, 0, 0])
    np.testing.assert_array_equal(masks["overlap"], [0, 0, 0, 1, 0])
    np.testing.assert_array_equal(masks["cell_strain"], [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(masks["stress_free"], [0, 0, 0, 0, 1])
    # the touching reference cell carries no force; the overlapped one does
    np.testing.assert_array_equal(exploration.stress_free(schema, arrays, law, tol)[[0, 3]], [True, False])


def test_probe_and_perturbation_distributions():
    settings = DatabaseSettings(chunk_size=20_000)
    d_eps = probing.probe_increments(settings, 0, 0, 20_000)
    magnitude = np.linalg.norm(d_eps, axis=1)
    assert magnitude.min() >= 1e-6 and magnitude.max() <= 1e-3
    focus = np.mean((magnitude >= 1e-5) & (magnitude <= 1e-4))
    assert 0.6 < focus < 0.7  # half the probes, plus a third of the wide log-uniform half
    np.testing.assert_array_equal(d_eps, probing.probe_increments(settings, 0, 0, 20_000))
    assert not np.array_equal(d_eps, probing.probe_increments(settings, 0, 1, 20_000))
    perturbed, zero, displacement = probing.perturbations(settings, 0, 0, 20_000, 4, 1.0)
    assert 0.24 < perturbed.mean() < 0.26 and 0.28 < zero[perturbed].mean() < 0.32 and not zero[~perturbed].any()
    assert not displacement[~perturbed].any()
    rms = np.sqrt((displacement[perturbed] ** 2).mean(axis=1))
    assert 5e-7 < np.median(rms) < 1e-4 and rms.max() < 5e-4 * 5


def test_exploration_is_generic_and_covers_the_shear_directions(h_db):
    data, attrs = h_db
    assert set(np.unique(data["states/alpha0_deg"]).round(6)) == {30.0, 55.0, 89.0}
    for psi in (135.0, 315.0):  # constant-volume directions from the precompressed states
        leg = ((data["states/direction_deg"] == psi) & (data["states/precompression"] == 1e-2)
               & (np.isclose(data["states/alpha0_deg"], 55.0)))
        assert leg.sum() >= 3
    iso = np.isnan(data["states/direction_deg"])
    np.testing.assert_array_equal(data["states/eps"][iso, 0], data["states/eps"][iso, 1])
    stops = json.loads(attrs["exploration_stops"])
    assert set(stops) == {*exploration.STOP_RULES, exploration.TURN_NOT_REACHED} and stops["stress_free"] > 0


def test_exploration_turns_legs_back(h_db):
    """Branches leave a state of their leg and strain back against it: the increment's
    component along the leg direction changes sign once, at the turn."""
    data, _ = h_db
    eps, path, turn = data["states/eps"], data["states/path_id"], data["states/turn_deg"]
    branch_paths = np.unique(path[~np.isnan(turn)])
    assert branch_paths.size >= 30
    first_increment = SMALL.sample_spacing / 2 ** SMALL.leg_refinement
    sign_changes = []
    for pid in branch_paths:
        mine = np.flatnonzero(path == pid)
        psi, pc = data["states/direction_deg"][mine[0]], data["states/precompression"][mine[0]]
        u = np.array([np.cos(np.radians(psi)), np.sin(np.radians(psi))])
        leg = np.flatnonzero((data["states/start_id"] == data["states/start_id"][mine[0]])
                             & (data["states/precompression"] == pc) & (data["states/direction_deg"] == psi)
                             & np.isnan(turn))
        distance = np.linalg.norm(eps[leg] - eps[mine[0]], axis=1)
        turn_state = leg[np.argmin(distance)]
        assert distance.min() == pytest.approx(first_increment, rel=1e-9)  # one increment from a leg state
        walked = np.concatenate([eps[leg[leg <= turn_state]], eps[mine]])
        along = np.diff(walked - pc, axis=0) @ u
        sign_changes.append(np.count_nonzero(np.diff(np.sign(along)) != 0))
        assert (walked[-1] - pc) @ u < (eps[turn_state] - pc) @ u
    assert np.all(np.array(sign_changes) == 1)
    negated = np.unique(path[turn == 180.0])
    assert 0.3 < negated.size / branch_paths.size < 0.7  # reversal_negated_fraction = 0.5
    assert np.all(np.abs(turn[~np.isnan(turn)]) >= SMALL.reversal_min_angle_deg)


def test_same_seed_same_datasets_whatever_threads(tmp_path):
    one, _ = run(tmp_path, "one.h5", threads=1)
    two, _ = run(tmp_path, "two.h5", threads=2, workers=2)
    (a, _), (b, _) = database.read_database(one), database.read_database(two)
    assert set(a) == set(b) and "states/turn_deg" in a
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_file_describes_its_mesostructure_and_schema(h_db, fine_db):
    for (data, attrs), meso in ((h_db, h_cell()), (fine_db, FINE)):
        assert attrs["format_version"] == 2 and attrs["mesostructure"] == describe(meso)
        assert attrs["mesostructure_sha256"] == description_sha256(describe(meso))
        assert describe(from_description(attrs["mesostructure"])) == describe(meso)
        schema = meso.schema()
        np.testing.assert_array_equal(data["schema/free_dofs"], schema.free_dofs)
        n = attrs["n_samples"]
        for group in database.STATE_GROUPS:
            assert data[f"{group}/free_position"].shape == (n, schema.n_free)
            assert data[f"{group}/shear_force"].shape == (n, schema.n_pairs)
    assert FINE.schema().n_free == 6 and not FINE.observables and not FINE.parameters
    assert not any(name.startswith("hcell/") or name == "alpha0_deg" for name in fine_db[0])
    assert "hcell/before_N1" in h_db[0] and "alpha0_deg" in h_db[0] and "hcell/before_closed1" not in h_db[0]


@pytest.mark.parametrize("which", ["h", "fine"])
def test_samples_recheck_against_the_dem(h_db, fine_db, which):
    """The stored before-state, the probe and the schema give the stored after-state exactly."""
    (data, attrs), meso = (h_db, h_cell()) if which == "h" else (fine_db, FINE)
    rows = np.concatenate([np.array([0, 17, 777, 1999]), np.flatnonzero(data["perturbed"])[:3]])
    recheck_against_the_dem(data, meso, rows)


def test_equilibrium_perturbed_mechanism_samples_are_kept_and_marked(h_db):
    data, attrs = h_db
    n = attrs["n_samples"]
    perturbed, mechanism = data["perturbed"], data["mechanism"]
    fmax = data["before/normal_force"].max(axis=1)
    unbalanced = np.abs(data["before/unbalanced"]).max(axis=1)
    loaded = fmax > 1.0
    tol = 1.01 * DemSettings().force_tolerance
    assert np.all(unbalanced[~perturbed & loaded] <= tol * fmax[~perturbed & loaded])  # relaxed states
    assert np.median(unbalanced[perturbed & loaded] / fmax[perturbed & loaded]) > 1e-4  # unbalanced states
    assert np.all(np.abs(data["after/unbalanced"]).max(axis=1)[data["converged"]]
                  <= tol * np.maximum(data["after/normal_force"].max(axis=1), 0.2)[data["converged"]])
    zero = np.all(data["d_eps"] == 0.0, axis=1)
    assert zero.any() and not np.any(zero & ~perturbed) and attrs["n_zero_probes"] == zero.sum()
    assert 0.2 * n < perturbed.sum() < 0.3 * n and attrs["n_perturbed"] == perturbed.sum()
    assert mechanism.any() and np.all(fmax[mechanism] <= 0.2) and attrs["n_mechanism"] == mechanism.sum()
    assert attrs["cleaned"] and not np.any(data["valid"] & ~data["converged"]) and data["valid"][mechanism].all()


def test_hcell_observables_follow_the_generic_state(h_db):
    data, _ = h_db
    for group in database.STATE_GROUPS:
        normal = data[f"{group}/normal_force"][:, 0]  # pair 1-2, float32 (probing.FLOAT32_FEATURES)
        np.testing.assert_array_equal(data[f"hcell/{group}_N1"].astype(normal.dtype), normal)
        np.testing.assert_array_equal(data[f"hcell/{group}_T1"], data[f"{group}/shear_force"][:, 0])
    np.testing.assert_array_equal(data["after/cell_size"][:, 0], data["before/cell_size"][:, 0]
                                  * (1.0 - data["d_eps"][:, 0]))


def test_unconverged_probes_are_flagged(tmp_path):
    strict = DemSettings(force_tolerance=1e-18, max_substeps=20_000)  # below round-off: loaded cells never converge
    settings = DatabaseSettings(samples=300, chunk_size=300, precompression=(0.0, 1e-3), n_directions=4,
                                sample_spacing=2e-3, leg_length=6e-3, reversal_arc=(2e-3, 6e-3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        written, _ = run(tmp_path, settings=settings, dem_settings=strict, clean=True)
    data, attrs = database.read_database(written)
    assert attrs["n_unconverged"] > 0 and attrs["removed_unconverged"] == attrs["n_unconverged"]
    assert not np.any(data["valid"] & ~data["converged"])
    assert json.loads(attrs["exploration_stops"])["unconverged"] > 0


def test_increments_beyond_max_substeps_are_refused_before_work(tmp_path):
    with pytest.raises(ValueError, match="needs more substeps than max_substeps"):
        run(tmp_path, dem_settings=DemSettings(max_substeps=1000))
    assert not generate.sidecar_path(tmp_path / "db.h5").exists()


def test_a_reversal_arc_without_a_sampled_state_is_refused_before_work(tmp_path):
    """A leg sampled at path lengths 0.005 to 0.045 has no state in (0.3001, 0.3002): the turns would have left
    the leg outside the arc asked for (before: silently at its last state)."""
    with pytest.raises(ValueError, match=r"reversal_arc = \(0.3001, 0.3002\) holds none of a leg's sampled path "
                                         r"lengths \(0.005, 0.015, 0.025, 0.035, \.\.\."):
        generate.generate(h_cell(), replace(SMALL, reversal_arc=(0.3001, 0.3002)), tmp_path / "db.h5", seed=3)
    assert not generate.sidecar_path(tmp_path / "db.h5").exists() and not (tmp_path / "db.h5").exists()
    assert exploration.turn_candidates(replace(SMALL, reversal_arc=(0.3001, 0.3002), reversal_legs=0)).size == 0


def test_same_seed_same_bytes_whatever_workers(tmp_path):
    first, _ = run(tmp_path, "a.h5")
    second, _ = run(tmp_path, "b.h5", workers=2, threads=1)
    assert first.read_bytes() == second.read_bytes()
    other, _ = run(tmp_path, "c.h5", seed=4)
    with h5py.File(first) as a, h5py.File(other) as c:
        assert not np.array_equal(a["d_eps"][()], c["d_eps"][()])


def test_resume_after_interruption_gives_identical_file(tmp_path):
    reference, _ = run(tmp_path, "ref.h5")
    stopped, out = run(tmp_path, "db.h5", max_chunks=2)
    assert stopped is None and not out.exists()
    sidecar = generate.sidecar_path(out)
    assert len(list(sidecar.glob("chunk_*.npz"))) == 2 and (sidecar / "states.npz").exists()
    (sidecar / "chunk_000003.npz.tmp").write_bytes(b"killed while writing")
    written, _ = run(tmp_path, "db.h5")
    assert written.read_bytes() == reference.read_bytes()
    assert not sidecar.exists()


def test_resume_refuses_other_options(tmp_path):
    run(tmp_path, max_chunks=1)
    with pytest.raises(ValueError, match="unfinished run with other options"):
        run(tmp_path, seed=5)
    written, _ = run(tmp_path, seed=5, discard_partial=True)
    assert database.read_database(written)[1]["seed"] == 5


def test_start_cells_must_share_the_learning_state(tmp_path):
    with pytest.raises(ValueError, match="does not share the learning state"):
        run(tmp_path, meso=h_cell(), starts=[h_cell(), LATERAL])


def exit_code(argv):
    """Exit code of the command line: argparse errors exit, other user errors return 2."""
    try:
        return generate_command.main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("args, message", [
    (["--samples", "-5"], "argument --samples: -5 must be >= 1"),
    (["--out", "{file}/db.h5"], "not a folder"),
    (["--out", "{existing}"], "exists; pass --overwrite to replace it"),
    (["--mesostructure", "{tmp}/missing.toml"], "missing.toml' is neither a file nor a spec"),
    (["--mesostructure", "hcell-fines:alpha0=50,ratio=0.9"], "fine grain ratio 0.9 does not fit the pore"),
    (["--mesostructure", "{file}"], "not valid"),
    (["--perturbed-fraction", "2"], "perturbed_fraction = 2 is outside [0, 1]"),
    (["--reversal-legs", "-1"], "reversal_legs = -1 must be >= 0"),
    (["--precompression", "0", "-0.001"], "needs finite strains >= 0"),
    (["--backend", "analytical"], "unrecognized arguments: --backend analytical"),
    (["--device", "cuda:7"], "--device cuda:7: no CUDA GPU on this machine"),
])
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, args, message):
    existing = tmp_path / "existing.h5"
    existing.write_bytes(b"precious")
    (tmp_path / "file").write_text("not a folder = [")
    base = ["--samples", "100", "--out", str(tmp_path / "new.h5")]
    args = [a.format(file=tmp_path / "file", existing=existing, tmp=tmp_path) for a in args]
    assert exit_code(base + args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # one error line (argparse prints its usage above it), no traceback
    assert message in err[-1] and "error: " in err[-1] and not any("Traceback" in line for line in err)
    assert sum("error" in line for line in err) == 1
    assert existing.read_bytes() == b"precious"
    assert not (tmp_path / "new.h5").exists()


def test_cli_writes_a_database_of_a_mesostructure_file(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    assert generate_command.main(["--mesostructure", str(DATA / "h_cell_lateral_0.7D.toml"), "--samples", "600",
                                  "--chunk-size", "300", "--n-directions", "4", "--seed", "1", "--out", str(out),
                                  "--clean", "--precompression", "0", "2e-3"]) == 0
    assert "600 samples in" in capsys.readouterr().out
    data, attrs = database.read_database(out)
    assert attrs["seed"] == 1 and attrs["cleaned"] and attrs["kn"] == ContactLaw().kn
    assert attrs["mesostructure"] == describe(LATERAL) and data["valid"].shape == (600,)
    assert set(np.unique(data["states/precompression"])) == {0.0, 2e-3}


def error_lines(capsys) -> list[str]:
    """The error lines on stderr (progress bars aside); fails on a traceback."""
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return [line for line in err.splitlines() if "error" in line]


def test_corrupt_sidecar_chunk_is_recomputed(tmp_path):
    reference, _ = run(tmp_path, "ref.h5")
    run(tmp_path, "db.h5", max_chunks=2)
    sidecar = generate.sidecar_path(tmp_path / "db.h5")
    (sidecar / "chunk_000001.npz").write_bytes(b"PK\x03\x04 truncated by a full disk")
    written, _ = run(tmp_path, "db.h5")
    assert written.read_bytes() == reference.read_bytes()


def test_exploration_is_checkpointed(tmp_path, monkeypatch):
    reference, _ = run(tmp_path, "ref.h5")
    stopped, out = run(tmp_path, "db.h5", max_chunks=0)
    sidecar = generate.sidecar_path(out)
    assert stopped is None and (sidecar / "states.npz").exists() and (sidecar / "start_000000.npz").exists()
    assert not list(sidecar.glob("chunk_*.npz"))

    def no_exploration(*args):
        raise AssertionError("the exploration ran again")

    monkeypatch.setattr(generate, "explore_starts", no_exploration)
    written, _ = run(tmp_path, "db.h5")
    assert written.read_bytes() == reference.read_bytes()


def test_second_run_on_the_same_output_exits_2(tmp_path, capsys):
    out = tmp_path / "db.h5"
    with output_lock(out):
        assert exit_code(["--mesostructure", str(DATA / "h_cell_lateral_0.7D.toml"), "--samples", "100",
                          "--out", str(out)]) == 2
    err = error_lines(capsys)
    assert len(err) == 1 and "is being written by another run" in err[0]
    assert not out.exists() and not generate.sidecar_path(out).exists()


def test_full_disk_is_one_line_and_leaves_no_partial_file(tmp_path, capsys, monkeypatch):
    out = tmp_path / "db.h5"
    real_savez = np.savez_compressed

    def full_disk_at_chunk_1(handle, **arrays):
        if Path(handle.name).name.startswith("chunk_000001"):
            handle.write(b"half a chunk")
            raise OSError(errno.ENOSPC, "No space left on device")
        real_savez(handle, **arrays)

    monkeypatch.setattr(shards.np, "savez_compressed", full_disk_at_chunk_1)
    argv = ["--mesostructure", str(DATA / "h_cell_lateral_0.7D.toml"), "--samples", "1500", "--chunk-size", "500",
            "--n-directions", "4", "--out", str(out)]
    assert exit_code(argv) == 2
    err = error_lines(capsys)
    assert len(err) == 1 and "no space left on the device" in err[0] and "chunk_000001.npz" in err[0]
    sidecar = generate.sidecar_path(out)
    assert not out.exists() and not list(sidecar.glob("*.tmp")) and not (sidecar / "chunk_000001.npz").exists()
    monkeypatch.setattr(shards.np, "savez_compressed", real_savez)  # space freed: the same command resumes

    def full_disk_in_hdf5(*args, **kwargs):
        raise OSError("Can't write data (file write failed: errno = 28, error message = 'No space left on device')")

    monkeypatch.setattr(database, "write_database", full_disk_in_hdf5)
    assert exit_code(argv) == 2
    err = error_lines(capsys)
    assert len(err) == 1 and "no space left on the device writing" in err[0] and str(out) in err[0]
    assert len(list(sidecar.glob("chunk_*.npz"))) == 3 and not out.exists()
    monkeypatch.undo()
    assert exit_code(argv) == 0
    assert database.read_database(out)[1]["n_samples"] == 1500


def test_a_builder_spec_names_the_mesostructure_of_the_database(tmp_path):
    """The database of a spec records the hash of the cell that the spec builds (what an ANN
    model of it is checked against in biaxial and the sweep)."""
    from warp_hcell.mesostructures.builders import resolve_mesostructure

    spec = "hcell-fines:alpha0=50,ratio=0.82"
    out = tmp_path / "db.h5"
    assert exit_code(["--mesostructure", spec, "--samples", "200", "--chunk-size", "100", "--n-directions", "4",
                      "--threads", "1", "--out", str(out)]) == 0
    attrs = database.read_database(out)[1]
    assert attrs["mesostructure_sha256"] == description_sha256(describe(resolve_mesostructure(spec)))
    assert attrs["mesostructure_sha256"] != description_sha256(describe(resolve_mesostructure(spec.replace("0.82", "0.8"))))


def test_unreachable_scheduler_exits_2_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(execution, "CONNECT_TIMEOUT_S", 1.0)
    out = tmp_path / "db.h5"
    assert exit_code(["--samples", "100", "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{free_port()}"]) == 2
    err = error_lines(capsys)
    assert len(err) == 1 and "cannot reach the Dask scheduler at tcp://127.0.0.1:" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_dask_scheduler_with_a_lost_worker_gives_the_local_file(tmp_path):
    """A real scheduler and two workers on 127.0.0.1; ``--scheduler`` generates 3e4 samples (60 chunks); one
    worker is killed mid-run; Dask reruns its tasks and the file is byte-identical to the
    in-process run of the same command."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(DATA.parents[1]), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", "warp_hcell.generate", "--mesostructure", str(DATA / "h_cell_lateral_0.7D.toml"),
               "--samples", "30000", "--chunk-size", "500", "--n-directions", "8", "--seed", "3", "--threads", "1"]
    local = tmp_path / "local.h5"
    subprocess.run([*command, "--out", str(local)], env=env, check=True, capture_output=True)
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    with local_cluster(2, env) as (address, procs):
        out = tmp_path / "dask.h5"
        sidecar = generate.sidecar_path(out)
        client = subprocess.Popen([*command, "--out", str(out), "--scheduler", address], **quiet)
        try:
            deadline = time.monotonic() + 120
            while len(list(sidecar.glob("chunk_*.npz"))) < 5 and time.monotonic() < deadline and client.poll() is None:
                time.sleep(0.05)
            done_at_kill = len(list(sidecar.glob("chunk_*.npz")))
            procs[1].kill()
            assert client.wait(timeout=300) == 0
        finally:
            client.kill()
            client.wait()
        assert 5 <= done_at_kill < 60
        assert out.read_bytes() == local.read_bytes()


def test_exploration_does_not_depend_on_how_start_cells_are_grouped():
    from warp_hcell.database import tasks

    starts = STARTS.build()
    physics = tasks.Physics(ContactLaw(), describe(h_cell()), DemSettings(), "cpu", 1)
    inputs = tasks.ExploreInputs(physics, tuple(describe(s) for s in starts), SMALL)
    together = tasks.explore_starts(inputs, (0, 1, 2))
    apart = [tasks.explore_starts(inputs, (k,)) for k in range(3)]
    assert set(together) == set(apart[0])
    for name, value in together.items():
        np.testing.assert_array_equal(value, np.concatenate([part[name] for part in apart]), err_msg=name)
    assert np.array_equal(np.unique(together["start_id"]), [0, 1, 2])
    stride = exploration.path_stride(SMALL)
    assert np.all(together["path_id"] // stride == together["start_id"])


@pytest.mark.slow
def test_explored_states_cover_constant_volume_homogenisation():
    """H-cells of every orientation sheared at constant volume to eps1 = 0.2 by the DEM after
    isotropic compression (p0 ~ 2e5 and 5.85e6 N/m), at alpha0 = 35, 40, 55 deg, stay as close
    to the default exploration's states as these are to each other: nearest-neighbour
    distances in (cell size / 1 m, normal and shear forces of the 15 pairs / 6e6 N)."""
    from warp_hcell.database import tasks

    settings = DatabaseSettings()
    meso = h_cell()
    starts = StartCells().build()
    physics = tasks.Physics(ContactLaw(), describe(meso), DemSettings(), "cpu", 2)
    inputs = tasks.ExploreInputs(physics, tuple(describe(s) for s in starts), settings)
    states = tasks.explore_starts(inputs, tuple(range(len(starts))))
    schema, law, tol = meso.schema(), ContactLaw(), DemSettings().contact_tolerance

    def features(cell_size, position, shear_force):
        ev = evaluate(schema, cell_size, free_coordinates(schema, position), shear_force, law, tol)
        return np.concatenate([cell_size, ev["normal_force"] / 6e6, ev["shear_force"] / 6e6], axis=1)

    def nearest(points, cloud, exclude=None):
        squared = (points**2).sum(axis=1)[:, None] + (cloud**2).sum(axis=1)[None, :] - 2.0 * points @ cloud.T
        if exclude is not None:
            squared[np.arange(points.shape[0]), exclude] = np.inf
        return np.sqrt(np.maximum(squared.min(axis=1), 0.0))

    explored = features(states["dem/cell_size"], states["dem/position"], states["dem/shear_force"])
    cell = DemCell(law, 0.5, threads=2)
    theta = np.arange(12) * np.pi / 12
    d_eps = 2e-3 * np.stack([np.cos(2.0 * theta), -np.cos(2.0 * theta)], axis=1)
    visited = []
    for alpha0 in (35.0, 40.0, 55.0):
        for eps_iso in (9e-4, 2.5e-2):
            state, _ = cell.step(cell.init_state(h_cell(alpha0), 12), np.full((12, 2), eps_iso))
            for k in range(100):
                state, _ = cell.step(state, d_eps)
                if k % 5 == 4:
                    arrays = cell.state_to_arrays(state)
                    visited.append(features(arrays["cell_size"], arrays["position"], arrays["shear_force"]))
    visited = np.concatenate(visited)
    distance = nearest(visited, explored)
    sample = np.random.default_rng(0).choice(explored.shape[0], 3000, replace=False)
    spacing = nearest(explored[sample], explored, exclude=sample)
    assert visited.shape[0] == 3 * 2 * 20 * 12
    assert np.median(distance) <= 1.5 * np.median(spacing), (np.median(distance), np.median(spacing))
    assert np.quantile(distance, 0.99) <= 1.5 * np.quantile(spacing, 0.99), (np.quantile(distance, 0.99),
                                                                            np.quantile(spacing, 0.99))
