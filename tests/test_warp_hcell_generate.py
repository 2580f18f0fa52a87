"""Tests of warp_hcell.generate: exploration, probes, re-check against the backend, determinism,
resume, the command line's errors, convergence flags. About 2e3 samples per run."""

import functools
import warnings

import h5py
import numpy as np
import pytest

from homogenization.backends import make_cell_model
from warp_hcell import database, generate
from warp_hcell.parameters import ContactLaw, DatabaseSettings, DemSettings

SMALL = DatabaseSettings(samples=2000, chunk_size=500, n_alpha0=2, alpha0_focus_deg=(55.0,),
                         precompression=(0.0, 1e-3, 1e-2), n_directions=8, sample_spacing=1e-2, leg_length=0.05,
                         leg_refinement=1)
META = {"backend": "analytical", "kn": ContactLaw().kn, "kt": ContactLaw().kt, "phi_g_deg": 30.0, "radius": 0.5}
ANALYTICAL = functools.partial(make_cell_model, "analytical")


@pytest.fixture(autouse=True)
def fixed_revision(monkeypatch):
    """Colleagues commit while tests run: pin the recorded git revision so files compare by bytes."""
    monkeypatch.setattr(generate, "git_revision", lambda: "pinned-for-tests")


def run(tmp_path, name="db.h5", *, factory=ANALYTICAL, settings=SMALL, **kwargs):
    out = tmp_path / name
    kwargs.setdefault("seed", 3)
    kwargs.setdefault("metadata_attrs", META)
    return generate.generate(factory, settings, out, **kwargs), out


@pytest.fixture(scope="module")
def dem_db(tmp_path_factory):
    """A small DEM database, cleaned, and the backend that made it."""
    factory = functools.partial(make_cell_model, "dem", threads=2)
    written, out = run(tmp_path_factory.mktemp("dem"), factory=factory, clean=True,
                       metadata_attrs={**META, "backend": "dem"})
    return database.read_database(written), factory()


def test_leg_limits_follow_direction():
    directions = generate.leg_directions(SMALL)
    arc = generate.leg_arc(SMALL)
    steps = generate.leg_steps(SMALL, directions, arc)
    np.testing.assert_allclose(arc, [5e-3, 1.5e-2, 2.5e-2, 3.5e-2, 4.5e-2])
    # psi = 45 deg (isotropic compression) is cut by the volumetric limit, psi = 135 deg is not
    assert steps[1] == 4  # 0.035 * sqrt(2) <= 0.05 < 0.045 * sqrt(2)
    assert steps[3] == arc.size
    cut = DatabaseSettings(leg_volumetric=0.01, leg_length=0.05, sample_spacing=1e-2, leg_refinement=0)
    assert generate.leg_steps(cut, directions, generate.leg_arc(cut))[1] == 0


def test_stop_rules():
    col = {name: i for i, name in enumerate(database.STATE_FEATURES)}
    table = np.ones((5, 13))
    table[:, col["alpha_deg"]] = [55.0, 29.9, 90.1, 55.0, 55.0]
    table[3, [col["closed1"], col["closed2"]]] = 0.0
    converged = np.array([True, True, True, True, False])
    np.testing.assert_array_equal(generate.admissible(table, converged), [True, False, False, False, False])
    table[0, col["N1"]] = np.nan
    assert not generate.admissible(table, converged)[0]


def test_probe_distribution():
    settings = DatabaseSettings(chunk_size=20_000)
    d_eps = generate.probe_increments(settings, 0, 0, 20_000)
    magnitude = np.linalg.norm(d_eps, axis=1)
    assert magnitude.min() >= 1e-6 and magnitude.max() <= 1e-3
    focus = np.mean((magnitude >= 1e-5) & (magnitude <= 1e-4))
    assert 0.6 < focus < 0.7  # half the probes, plus a third of the wide log-uniform half
    quadrant = np.histogram(np.arctan2(d_eps[:, 1], d_eps[:, 0]), bins=4, range=(-np.pi, np.pi))[0]
    assert quadrant.min() > 0.23 * d_eps.shape[0]
    np.testing.assert_array_equal(d_eps, generate.probe_increments(settings, 0, 0, 20_000))
    assert not np.array_equal(d_eps, generate.probe_increments(settings, 0, 1, 20_000))


def test_exploration_covers_homogenisation_paths():
    states = generate.explore(ANALYTICAL(), SMALL)
    obs = states["observables"]
    alpha = obs[:, database.STATE_FEATURES.index("alpha_deg")]
    assert np.all((alpha > 30.0 - 1e-9) & (alpha <= 90.0))
    assert set(np.unique(states["alpha0_deg"])) == {30.0, 55.0, 89.0}
    # constant-volume directions from the precompressed states are explored
    for psi in (135.0, 315.0):
        leg = (states["direction_deg"] == psi) & (states["precompression"] == 1e-2) & (states["alpha0_deg"] == 55.0)
        assert leg.sum() >= 3
    # every leg starts from a sampled isotropic state of its alpha0
    iso = np.isnan(states["direction_deg"])
    np.testing.assert_array_equal(states["eps_local"][iso, 0], states["eps_local"][iso, 1])
    assert np.all(np.isin(states["precompression"][~iso], states["precompression"][iso]))


def test_dem_samples_recheck_against_backend(dem_db):
    (samples, states, attrs), cell = dem_db
    assert attrs["backend"] == "dem" and samples["inputs"].shape == (2000, 8)
    backend = {name[len("backend/"):]: value for name, value in states.items() if name.startswith("backend/")}
    rows = np.array([0, 17, 777, 1999])
    index = samples["state_index"][rows]
    restored = cell.state_from_arrays({name: value[index] for name, value in backend.items()})
    pre = database.state_table(cell.observables(restored))
    np.testing.assert_array_equal(pre, samples["pre_state"][rows])
    new, _ = cell.step(restored, samples["inputs"][rows, :2])
    np.testing.assert_array_equal(database.state_table(cell.observables(new)), samples["post_state"][rows])


def test_sample_columns_are_consistent(dem_db):
    (samples, states, _), _ = dem_db
    col = {name: i for i, name in enumerate(database.STATE_FEATURES)}
    pre, post, d_eps = samples["pre_state"], samples["post_state"], samples["inputs"][:, :2]
    np.testing.assert_array_equal(samples["inputs"][:, 2:], pre[:, [col[n] for n in database.INPUT_FEATURES[2:]]])
    np.testing.assert_array_equal(samples["outputs"], post[:, [col[n] for n in database.OUTPUT_FEATURES]])
    np.testing.assert_array_equal(post[:, col["l1"]], pre[:, col["l1"]] * (1.0 - d_eps[:, 0]))
    np.testing.assert_array_equal(samples["path_id"], states["path_id"][samples["state_index"]])
    np.testing.assert_array_equal(samples["alpha0_deg"], states["alpha0_deg"][samples["state_index"]])
    per_state = np.bincount(samples["state_index"])
    assert per_state[per_state > 0].max() - per_state[per_state > 0].min() <= 1


def test_every_sample_converged_or_flagged(dem_db):
    (samples, _, attrs), _ = dem_db
    assert attrs["cleaned"] and attrs["n_unconverged"] == np.count_nonzero(~samples["converged"])
    assert not np.any(samples["valid"] & ~samples["converged"])
    assert attrs["n_valid"] == np.count_nonzero(samples["valid"]) > 1900


def test_unconverged_probes_are_flagged(tmp_path):
    strict = DemSettings(force_tolerance=1e-14, max_substeps=20_000)
    factory = functools.partial(make_cell_model, "dem", settings=strict)
    settings = DatabaseSettings(samples=300, chunk_size=300, n_alpha0=1, alpha0_focus_deg=(), precompression=(0.0,),
                                n_directions=4, sample_spacing=2e-3, leg_length=6e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        written, _ = run(tmp_path, factory=factory, settings=settings, clean=True)
    samples, _, attrs = database.read_database(written)
    assert attrs["n_unconverged"] > 0 and attrs["removed_unconverged"] == attrs["n_unconverged"]
    assert not np.any(samples["valid"] & ~samples["converged"])


def test_same_seed_same_bytes_whatever_workers(tmp_path):
    first, _ = run(tmp_path, "a.h5")
    second, _ = run(tmp_path, "b.h5", workers=2)
    assert first.read_bytes() == second.read_bytes()
    other, _ = run(tmp_path, "c.h5", seed=4)
    with h5py.File(first) as a, h5py.File(other) as c:
        assert not np.array_equal(a["inputs"][()], c["inputs"][()])


def test_resume_after_interruption_gives_identical_file(tmp_path):
    reference, _ = run(tmp_path, "ref.h5")
    stopped, out = run(tmp_path, "db.h5", max_chunks=2)
    assert stopped is None and not out.exists()
    sidecar = generate.sidecar_path(out)
    assert len(list(sidecar.glob("chunk_*.npz"))) == 2
    (sidecar / "chunk_000003.npz.tmp").write_bytes(b"killed while writing")
    written, _ = run(tmp_path, "db.h5")
    assert written.read_bytes() == reference.read_bytes()
    assert not sidecar.exists()


def test_resume_refuses_other_options(tmp_path):
    run(tmp_path, max_chunks=1)
    with pytest.raises(ValueError, match="unfinished run with other options"):
        run(tmp_path, seed=5)
    written, _ = run(tmp_path, seed=5, discard_partial=True)
    assert database.read_database(written)[2]["seed"] == 5


def exit_code(argv):
    """Exit code of the command line: argparse errors exit, other user errors return 2."""
    try:
        return generate.main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("args, message", [
    (["--samples", "-5"], "argument --samples: -5 must be >= 1"),
    (["--out", "{file}/db.h5"], "not a folder"),
    (["--out", "{existing}"], "exists; pass --overwrite to replace it"),
    (["--backend", "dem", "--mesostructure", "{tmp}/missing.toml"], "missing.toml does not exist"),
    (["--mesostructure", "{tmp}/missing.toml"], "--mesostructure needs --backend dem"),
    (["--backend", "ann"], "invalid choice: 'ann'"),
])
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, args, message):
    existing = tmp_path / "existing.h5"
    existing.write_bytes(b"precious")
    (tmp_path / "file").write_text("not a folder")
    base = ["--samples", "100", "--backend", "analytical", "--out", str(tmp_path / "new.h5")]
    args = [a.format(file=tmp_path / "file", existing=existing, tmp=tmp_path) for a in args]
    assert exit_code(base + args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # one error line (argparse prints its usage above it), no traceback
    assert message in err[-1] and "error: " in err[-1] and not any("Traceback" in line for line in err)
    assert sum("error" in line for line in err) == 1
    assert existing.read_bytes() == b"precious"
    assert not (tmp_path / "new.h5").exists()


def test_cli_writes_a_cleaned_database(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    assert generate.main(["--samples", "1000", "--chunk-size", "400", "--backend", "analytical", "--n-alpha0", "2",
                          "--n-directions", "4", "--seed", "1", "--out", str(out), "--clean"]) == 0
    assert "1000 samples in" in capsys.readouterr().out
    samples, _, attrs = database.read_database(out)
    assert attrs["seed"] == 1 and attrs["cleaned"] and attrs["backend"] == "analytical"
    assert attrs["kn"] == ContactLaw().kn and samples["valid"].shape == (1000,)


def test_explored_states_cover_constant_volume_homogenisation():
    """Cells of every orientation sheared at constant volume to eps1 = 0.3 after isotropic
    compression (p0 ~ 2e5 and 5.85e6 N/m) stay close to an explored state: distance in
    (alpha / 60 deg, forces / 6e6 N, lengths / 1 m) comparable to the database's own spacing."""
    cell = ANALYTICAL()
    states = generate.explore(cell, DatabaseSettings())
    col = [database.STATE_FEATURES.index(n) for n in ("alpha_deg", "N1", "N2", "T1", "l1", "l2")]
    scale = np.array([60.0, 6e6, 6e6, 6e6, 1.0, 1.0])
    explored = states["observables"][:, col] / scale
    theta = np.arange(12) * np.pi / 12
    d_eps = 2e-3 * np.stack([np.cos(2.0 * theta), -np.cos(2.0 * theta)], axis=1)
    visited = []
    for alpha0 in (35.0, 40.0, 55.0):
        for eps_iso in (9e-4, 2.5e-2):
            state, _ = cell.step(cell.init_state(alpha0, 12), np.full((12, 2), eps_iso))
            for k in range(150):
                state, _ = cell.step(state, d_eps)
                if k % 6 == 5:
                    obs = cell.observables(state)
                    keep = (obs["closed1"] | obs["closed2"]) & (obs["alpha_deg"] > 30.0) & (obs["alpha_deg"] < 90.0)
                    visited.append(database.state_table(obs)[keep][:, col] / scale)
    visited = np.concatenate(visited)
    squared = (visited**2).sum(axis=1)[:, None] + (explored**2).sum(axis=1)[None, :] - 2.0 * visited @ explored.T
    distance = np.sqrt(np.maximum(squared.min(axis=1), 0.0))
    assert visited.shape[0] > 500
    assert np.median(distance) < 0.02 and np.quantile(distance, 0.99) < 0.1
