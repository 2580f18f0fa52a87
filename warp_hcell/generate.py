"""python -m warp_hcell.generate --samples 300000 --seed 0 --out runs/db.h5 [--backend dem|analytical]

Generates the learning database of the meso-ANN (spec section 11; file format in
docs/database_format.md, implemented by ``warp_hcell.database``).

Design
------
1. Exploration (deterministic, no randomness). For every initial opening angle of a grid
   (``DatabaseSettings.n_alpha0`` angles evenly spaced in [30, 89] deg plus the angles of the
   homogenisation runs, 35, 40 and 55 deg), one isotropic path compresses the touching cell
   (d_eps_n = d_eps_t) through the precompression levels (0 to 3e-2; p ~ 2.2e8 N/m x eps,
   so 1e-3 is p0 ~ 2e5 N/m and 2e-2 to 3e-2 is p0 = 5.85e6 N/m). From the state at each
   level, proportional legs leave in ``n_directions`` directions psi of the (eps_n, eps_t)
   plane (all directions: cells close, open, slide and lose contacts). A leg runs until its
   path length reaches ``leg_length`` (0.45 >= sqrt(2) x 0.3: constant-volume shearing to
   eps1 = 0.3 moves a cell along psi = -45 or 135 deg by up to 0.3 sqrt(2)), or its
   volumetric strain change reaches ``leg_volumetric``. This tree of paths covers what the
   homogenisation visits: isotropic compression to p0 = 2e5 or 5.85e6 N/m, then
   constant-volume (psi = -45 / 135 deg) or drained (other psi) shearing of cells of every
   orientation, at alpha0 = 35, 40, 55 deg and around. Every path is one batch member and
   all active paths advance as ONE batch per increment, and each state reached is sampled.
   The increment is ``sample_spacing`` (path length), except at the start of a leg where
   it starts at sample_spacing / 2**leg_refinement and doubles (finer sampling after the
   change of direction, where the response changes fastest). A path stops, and is no
   longer sampled, when a stop rule fires: alpha outside [30, 90] deg, all contacts open
   (stress-free mechanism), backend not converged, or a non-finite value. With
   ``--mesostructure`` (DEM) every path starts from the file's cell, so the alpha0 grid
   reduces to that cell's opening angle.
2. Probing (seeded). Sample i probes state ``order[i % n_states]`` (``order`` a seeded
   permutation, so each state gets the same number of probes to within one) with an
   increment of uniform direction in the (d_eps_n, d_eps_t) plane and a log-uniform
   magnitude: with probability ``probe_focus_fraction`` in [1e-5, 1e-4] (the increments
   the ANN is mostly used with), otherwise in [1e-6, 1e-3]. Samples are computed in chunks
   of ``chunk_size``; all probes of a chunk are ONE batch: ``take`` restores their states
   from the pool of sampled states, one ``step`` applies the probes.
3. Storage, resume, determinism. Completed work goes to a sidecar folder ``<out>.parts``
   (``run.json``, ``states.npz``, one ``chunk_XXXXXX.npz`` per chunk, each file written to a
   temporary name and renamed), so an interrupted run resumes where it stopped. When all
   chunks exist, the HDF5 file is written to a temporary file and renamed onto ``--out``;
   the sidecar is then removed. Chunk c draws its probes from the seed and c only, and a
   backend cell's result does not depend on its batch, so the file is bit-identical for a
   given seed whatever ``--workers`` and however often the run was interrupted.
4. Cleaning is an explicit step (``--clean`` here, or ``python -m warp_hcell.clean``),
   documented in ``warp_hcell.clean``.

Import direction: the generator core (``explore``, ``compute_chunk``, ``generate``) is
duck-typed: it takes any object implementing the cell-model protocol (``init_state``,
``step``, ``observables``, ``take``, ``state_to_arrays``, ``state_from_arrays``), or a
picklable factory of one, and imports nothing from ``homogenization``. Only ``main`` (the
command line, the composition root) imports ``homogenization.backends`` to build the
chosen backend, lazily inside the function, so importing any ``warp_hcell`` module never
imports ``homogenization``.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from warp_hcell import clean as cleaning
from warp_hcell import database
from warp_hcell.cli import UserError, check_output_path, common_parser, positive_float, positive_int, run_main
from warp_hcell.parameters import DatabaseSettings
from warp_hcell.provenance import git_revision, package_versions

BACKEND_PREFIX = "backend/"
"""Prefix of the backend's own state arrays among the sampled-state arrays."""
EQUILIBRIUM_RTOL = 1e-6
"""Equilibrium residual of grain 2, relative to the largest normal force, below which a
cell of a backend without its own per-cell flag counts as converged [-]."""
GENERATOR_BACKENDS = ("dem", "analytical")
"""``--backend`` choices: the registry names of the backends that can generate a database."""


# -- exploration ------------------------------------------------------------------------
def alpha0_grid(settings: DatabaseSettings) -> np.ndarray:
    """Initial opening angles of the exploration [deg], sorted, shape (n,): the even grid
    plus the focus angles."""
    grid = np.linspace(settings.alpha0_min_deg, settings.alpha0_max_deg, settings.n_alpha0)
    return np.unique(np.concatenate([grid, np.asarray(settings.alpha0_focus_deg, dtype=np.float64)]))


def leg_directions(settings: DatabaseSettings) -> np.ndarray:
    """Unit directions (d_eps_n, d_eps_t) of the legs, psi_k = 2 pi k / n, shape (n, 2)."""
    psi = 2.0 * np.pi * np.arange(settings.n_directions) / settings.n_directions
    return np.stack([np.cos(psi), np.sin(psi)], axis=1)


def leg_arc(settings: DatabaseSettings) -> np.ndarray:
    """Path length [-] of a leg after each of its increments, shape (K,), increasing.

    The first increment is sample_spacing / 2**leg_refinement; increments then double up to
    sample_spacing and stay there until leg_length: the sampling is finer just after the
    change of direction, where the response changes fastest.
    """
    spacing = settings.sample_spacing
    first = spacing * 0.5 ** np.arange(settings.leg_refinement, 0, -1)
    n_uniform = math.floor(settings.leg_length / spacing * (1.0 + 1e-12))
    arc = np.concatenate([np.cumsum(first), first.sum() + spacing * np.arange(1, n_uniform + 1)])
    return arc[arc <= settings.leg_length * (1.0 + 1e-12)]


def leg_steps(settings: DatabaseSettings, directions: np.ndarray, arc: np.ndarray) -> np.ndarray:
    """Increments of each leg allowed by the path-length and volumetric limits, shape (n,) int64.

    Args:
        directions: unit leg directions (d_eps_n, d_eps_t), shape (n, 2).
        arc: ``leg_arc`` of the settings, shape (K,).
    """
    volumetric = np.abs(directions.sum(axis=1))
    reach = settings.leg_volumetric / np.maximum(volumetric, 1e-300) * (1.0 + 1e-12)
    return np.searchsorted(arc, reach, side="right").astype(np.int64)


def converged_cells(observables: Mapping[str, np.ndarray]) -> np.ndarray:
    """Per-cell convergence of the step that produced a state, shape (n_cells,) bool.

    Iterative backends that report it per cell (``observables["converged"]``, the DEM) are
    trusted; otherwise a cell counts as converged when grain 2 is in equilibrium along n
    (spec section 5): |N2 - N1 cos a - T1 sin a| <= EQUILIBRIUM_RTOL max(N1, N2).
    """
    if "converged" in observables:
        return np.asarray(observables["converged"], dtype=bool)
    alpha = np.radians(observables["alpha_deg"])
    N1, N2, T1 = observables["N1"], observables["N2"], observables["T1"]
    residual = np.abs(N2 - N1 * np.cos(alpha) - T1 * np.sin(alpha))
    return residual <= EQUILIBRIUM_RTOL * np.maximum(N1, N2)


def admissible(table: np.ndarray, converged: np.ndarray) -> np.ndarray:
    """Stop rules of the exploration, negated: True where a path may go on and be sampled.

    Args:
        table: states, shape (n, 13), columns ``database.STATE_FEATURES``.
        converged: per-cell convergence of the step that produced them, shape (n,).

    Returns:
        bool (n,): converged, finite, alpha in [30, 90] deg (``clean.alpha_in_range``) and
        at least one contact closed.
    """
    col = {name: i for i, name in enumerate(database.STATE_FEATURES)}
    closed = (table[:, col["closed1"]] > 0.0) | (table[:, col["closed2"]] > 0.0)
    in_range = cleaning.alpha_in_range(table[:, col["alpha_deg"]])
    return converged & np.isfinite(table).all(axis=1) & in_range & closed


def _record(cell_model, state, observables: Mapping[str, np.ndarray], active: np.ndarray,
            step: int) -> dict[str, np.ndarray]:
    """Sampled-state record: ``cell`` and ``step`` (int64), ``observables`` (n, 13), backend arrays."""
    record = {"cell": active, "step": np.full(active.size, step, np.int64),
              "observables": database.state_table(observables)}
    record.update({BACKEND_PREFIX + name: value for name, value in cell_model.state_to_arrays(state).items()})
    return record


def _walk(cell_model, state, increments: np.ndarray, n_steps: np.ndarray, label: str, *,
          sample_start: bool) -> dict[str, np.ndarray]:
    """Advance cells along their own increments, one batch per increment, sampling each state.

    The start states are admissible by construction (touching states, or states sampled
    before). A path stops at its first inadmissible state (not sampled) or after
    ``n_steps`` increments.

    Args:
        cell_model: a cell-model backend.
        state: the start states, n_cells cells.
        increments: (d_eps_n, d_eps_t) [-] of increment k of cell i, shape (n_cells, K, 2)
            (a broadcast view is fine), compression positive.
        n_steps: increments allowed per cell, shape (n_cells,) int, <= K.
        label: progress-bar label.
        sample_start: also sample the start states (step 0).

    Returns:
        The sampled states: ``cell`` (walk index) and ``step`` (increments done) int64 (n,),
        ``observables`` (n, 13) columns ``database.STATE_FEATURES``, and the backend's
        ``state_to_arrays`` prefixed with ``BACKEND_PREFIX``.
    """
    active = np.arange(increments.shape[0])
    parts = [_record(cell_model, state, cell_model.observables(state), active, 0)] if sample_start else []
    for k in tqdm(range(int(n_steps.max(initial=0))), desc=label, unit="increment", leave=False):
        going = np.flatnonzero(n_steps[active] > k)
        if going.size < active.size:
            state, active = cell_model.take(state, going), active[going]
        if not active.size:
            break
        state, response = cell_model.step(state, np.ascontiguousarray(increments[active, k]))
        observables = cell_model.observables(state)
        keep = np.flatnonzero(admissible(database.state_table(observables),
                                         converged_cells(observables)))
        state, active = cell_model.take(state, keep), active[keep]
        parts.append(_record(cell_model, state, {name: value[keep] for name, value in observables.items()},
                             active, k + 1))
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def explore(cell_model, settings: DatabaseSettings) -> dict[str, np.ndarray]:
    """Run the exploration tree (module docstring, step 1) and return the sampled states.

    Args:
        cell_model: a cell-model backend (H-cell observables).
        settings: generator settings.

    Returns:
        Arrays with first axis n_states: the backend's state arrays (names prefixed with
        ``BACKEND_PREFIX``), ``observables`` (n_states, 13) columns
        ``database.STATE_FEATURES``, ``path_id`` int64, ``alpha0_deg`` [deg],
        ``precompression`` [-] (isotropic strain eps_n = eps_t the leg started from; the
        current one on the isotropic paths), ``direction_deg`` [deg] (leg direction psi in
        the (eps_n, eps_t) plane; NaN on the isotropic paths), and ``eps_local``
        (n_states, 2) [-], the strain (eps_n, eps_t) summed from the touching state,
        compression positive. Path ids: 0..n_alpha0-1 the isotropic paths, then the legs.
    """
    alpha0 = alpha0_grid(settings)
    n_alpha0 = alpha0.size
    levels = np.unique(np.asarray(settings.precompression, dtype=np.float64))
    iso_strain = np.union1d(levels, np.arange(0.0, levels[-1], settings.sample_spacing / math.sqrt(2.0)))
    iso_increments = np.repeat(np.diff(iso_strain)[None, :, None], 2, axis=2)
    iso = _walk(cell_model, cell_model.init_state(alpha0, n_alpha0),
                np.broadcast_to(iso_increments, (n_alpha0, *iso_increments.shape[1:])),
                np.full(n_alpha0, iso_increments.shape[1]), "isotropic paths", sample_start=True)
    iso_eps = iso_strain[iso.pop("step")]
    cell = iso.pop("cell")
    iso.update(path_id=cell, alpha0_deg=alpha0[cell], precompression=iso_eps,
               direction_deg=np.full(iso_eps.size, np.nan), eps_local=np.repeat(iso_eps[:, None], 2, axis=1))

    origin = np.flatnonzero(np.isin(iso_eps, levels))
    directions = leg_directions(settings)
    n_dir = directions.shape[0]
    leg_origin = np.repeat(origin, n_dir)
    leg_dir = np.tile(np.arange(n_dir), origin.size)
    arc = leg_arc(settings)
    steps = leg_steps(settings, directions, arc)[leg_dir]
    starts = cell_model.state_from_arrays({name: value[leg_origin] for name, value in backend_arrays(iso).items()})
    increments = np.diff(arc, prepend=0.0)[None, :, None] * directions[leg_dir][:, None, :]
    legs = _walk(cell_model, starts, increments, steps, "proportional legs", sample_start=False)
    step, cell = legs.pop("step"), legs.pop("cell")
    start = leg_origin[cell]
    legs.update(
        path_id=n_alpha0 + cell,
        alpha0_deg=iso["alpha0_deg"][start],
        precompression=iso_eps[start],
        direction_deg=360.0 * leg_dir[cell] / n_dir,
        eps_local=iso["eps_local"][start] + arc[step - 1, None] * directions[leg_dir[cell]],
    )
    return {name: np.concatenate([iso[name], legs[name]]) for name in iso}


# -- probing ----------------------------------------------------------------------------
def _rng(seed: int, *key: int) -> np.random.Generator:
    """Generator of stream ``key`` of ``seed`` (independent of any other stream)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def state_order(seed: int, n_states: int) -> np.ndarray:
    """Seeded permutation of the sampled states: sample i probes state ``order[i % n_states]``."""
    return _rng(seed, 0).permutation(n_states)


def chunk_bounds(settings: DatabaseSettings, chunk: int) -> tuple[int, int]:
    """Sample range [start, stop) of chunk ``chunk``."""
    start = chunk * settings.chunk_size
    return start, min(start + settings.chunk_size, settings.samples)


def chunk_samples(settings: DatabaseSettings, chunk: int) -> int:
    """Number of samples in chunk ``chunk``."""
    start, stop = chunk_bounds(settings, chunk)
    return stop - start


def n_chunks(settings: DatabaseSettings) -> int:
    """Number of chunks of the database."""
    return -(-settings.samples // settings.chunk_size)


def probe_increments(settings: DatabaseSettings, seed: int, chunk: int, n: int) -> np.ndarray:
    """Probes (d_eps_n, d_eps_t) [-] of chunk ``chunk``, shape (n, 2), compression positive.

    Direction uniform in [0, 2 pi); magnitude (Euclidean norm) log-uniform in
    [probe_focus_min, probe_focus_max] with probability ``probe_focus_fraction``, else in
    [probe_min, probe_max]. Drawn from stream (1, chunk) of ``seed`` only.
    """
    rng = _rng(seed, 1, chunk)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    focus = rng.random(n) < settings.probe_focus_fraction
    lo = np.where(focus, settings.probe_focus_min, settings.probe_min)
    hi = np.where(focus, settings.probe_focus_max, settings.probe_max)
    magnitude = np.exp(np.log(lo) + rng.random(n) * (np.log(hi) - np.log(lo)))
    return magnitude[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def compute_chunk(cell_model, pool, states: Mapping[str, np.ndarray], settings: DatabaseSettings, seed: int,
                  chunk: int) -> dict[str, np.ndarray]:
    """All samples of one chunk, computed as ONE batch.

    Args:
        cell_model: the backend that explored ``states``.
        pool: ``cell_model.state_from_arrays`` of the sampled states (n_states cells).
        states: ``explore`` output.
        settings, seed: generator settings and seed.
        chunk: chunk index.

    Returns:
        The per-sample datasets of ``database.SAMPLE_DATASETS`` except ``valid``.
    """
    start, stop = chunk_bounds(settings, chunk)
    n_states = states["path_id"].size
    sample = np.arange(start, stop)
    index = state_order(seed, n_states)[sample % n_states]
    d_eps = probe_increments(settings, seed, chunk, sample.size)
    new, _ = cell_model.step(cell_model.take(pool, index), d_eps)
    observables = cell_model.observables(new)
    out = database.sample_arrays(d_eps, states["observables"][index], database.state_table(observables))
    out.update({
        "path_id": states["path_id"][index],
        "probe_id": (sample // n_states).astype(np.int64),
        "alpha0_deg": states["alpha0_deg"][index],
        "state_index": index.astype(np.int64),
        "converged": converged_cells(observables),
    })
    return out


# -- files: sidecar, resume, assembly ----------------------------------------------------
def _save_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` atomically (temporary name, then rename)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        np.savez(handle, **{name.replace("/", ":"): value for name, value in arrays.items()})
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {name.replace(":", "/"): data[name] for name in data.files}


def backend_arrays(states: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The backend's state arrays among the ``explore`` output (prefix ``backend/`` removed)."""
    return {name[len(BACKEND_PREFIX):]: value for name, value in states.items() if name.startswith(BACKEND_PREFIX)}


def sidecar_path(out: Path) -> Path:
    """Folder holding the completed work of an unfinished run writing ``out``."""
    return out.with_name(out.name + ".parts")


def _chunk_file(sidecar: Path, chunk: int) -> Path:
    return sidecar / f"chunk_{chunk:06d}.npz"


_WORKER: dict[str, Any] = {}


def _worker_init(factory: Callable[[], Any], states_file: str) -> None:
    """Process-pool initializer: build the backend and the pool of sampled states once."""
    cell_model = factory()
    states = _load_npz(Path(states_file))
    pool = cell_model.state_from_arrays(backend_arrays(states))
    _WORKER.update(cell_model=cell_model, pool=pool, states=states)


def _worker_chunk(settings: DatabaseSettings, seed: int, chunk: int, sidecar: str) -> int:
    """Compute chunk ``chunk`` in a worker process, save it to the sidecar, return its size."""
    arrays = compute_chunk(_WORKER["cell_model"], _WORKER["pool"], _WORKER["states"], settings, seed, chunk)
    _save_npz(_chunk_file(Path(sidecar), chunk), arrays)
    return chunk_samples(settings, chunk)


def run_description(settings: DatabaseSettings, seed: int, metadata_attrs: Mapping[str, Any]) -> dict[str, Any]:
    """What identifies a run (resuming requires the same): settings, seed, physics, backend."""
    return json.loads(json.dumps({"generator": asdict(settings), "seed": int(seed), "metadata": dict(metadata_attrs)}))


def _open_sidecar(sidecar: Path, description: Mapping[str, Any], discard_partial: bool) -> dict[str, Any]:
    """Start or resume the run recorded in ``sidecar/run.json``; returns its record.

    The record keeps the git revision and versions of the run's start, so a resumed run
    writes the same attrs as an uninterrupted one.
    """
    run_file = sidecar / "run.json"
    if run_file.exists() and json.loads(run_file.read_text())["description"] != description:
        if not discard_partial:
            raise ValueError(f"{sidecar} holds an unfinished run with other options; "
                             f"rerun it with the same options or pass --overwrite to discard it")
        shutil.rmtree(sidecar)
    if not run_file.exists():
        sidecar.mkdir(parents=True, exist_ok=True)
        run = {"description": description, "git_revision": git_revision(), "versions": package_versions()}
        tmp = run_file.with_name("run.json.tmp")
        tmp.write_text(json.dumps(run, indent=1, sort_keys=True))
        os.replace(tmp, run_file)
    return json.loads(run_file.read_text())


def _compute_chunks(factory: Callable[[], Any], cell_model, states_file: Path, settings: DatabaseSettings,
                    seed: int, todo: Sequence[int], workers: int, bar: tqdm) -> None:
    """Compute chunks ``todo`` into the sidecar, in this process or in ``workers`` processes."""
    sidecar = states_file.parent
    if workers <= 1:
        states = _load_npz(states_file)
        pool = cell_model.state_from_arrays(backend_arrays(states))
        for chunk in todo:
            _save_npz(_chunk_file(sidecar, chunk), compute_chunk(cell_model, pool, states, settings, seed, chunk))
            bar.update(chunk_samples(settings, chunk))
        return
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_init,
                             initargs=(factory, str(states_file))) as executor:
        jobs = [executor.submit(_worker_chunk, settings, seed, chunk, str(sidecar)) for chunk in todo]
        try:
            for job in jobs:
                bar.update(job.result())
        finally:
            for job in jobs:
                job.cancel()


def _assemble(out: Path, sidecar: Path, settings: DatabaseSettings, seed: int, run: Mapping[str, Any],
              metadata_attrs: Mapping[str, Any], clean: bool) -> None:
    """Write the database from the sidecar's chunks to a temporary file, rename it onto ``out``."""
    states = _load_npz(sidecar / "states.npz")
    chunks = [_load_npz(_chunk_file(sidecar, c)) for c in range(n_chunks(settings))]
    samples = {name: np.concatenate([part[name] for part in chunks]) for name in chunks[0]}
    attrs = {
        "format": database.FORMAT,
        "format_version": database.FORMAT_VERSION,
        "sign_convention": database.SIGN_CONVENTION,
        "seed": int(seed),
        **{f"version_{name.replace('-', '_')}": value for name, value in run["versions"].items()},
        "git_revision": run["git_revision"],
        **metadata_attrs,
        "generator": asdict(settings),
        "n_samples": int(settings.samples),
        "n_states": int(states["path_id"].size),
        "n_paths": int(np.unique(states["path_id"]).size),
        "n_unconverged": int(np.count_nonzero(~samples["converged"])),
    }
    samples["valid"], cleaning_attrs = cleaning.clean_samples(samples) if clean else cleaning.not_cleaned(samples)
    attrs.update(cleaning_attrs)
    database.write_database(out, samples, states, attrs)


def generate(
    factory: Callable[[], Any],
    settings: DatabaseSettings,
    out: Path,
    *,
    seed: int,
    metadata_attrs: Mapping[str, Any],
    workers: int = 1,
    clean: bool = False,
    max_chunks: int | None = None,
    discard_partial: bool = False,
) -> Path | None:
    """Generate (or resume) a database and write it to ``out``.

    Args:
        factory: picklable callable returning a cell-model backend (called once in this
            process, and once per worker process).
        settings: generator settings.
        out: database file to write (replaced atomically at the end).
        seed: seed of the probes and of the state order.
        metadata_attrs: root attributes describing the physics and the backend (contact law
            ``kn, kt, phi_g_deg``, ``radius``, ``backend``, DEM settings, mesostructure);
            JSON-serialisable; part of the run identity checked on resume.
        workers: processes computing chunks in parallel (the result does not depend on it).
        clean: apply ``warp_hcell.clean`` before writing.
        max_chunks: compute at most this many new chunks, then return None without writing
            ``out`` (the run resumes later; used to split a run into sessions).
        discard_partial: drop an unfinished run of other options found in the sidecar
            instead of refusing.

    Returns:
        ``out`` once written, or None when stopped by ``max_chunks``.

    Raises:
        ValueError: (one line) the sidecar holds an unfinished run with other options.
    """
    out = Path(out)
    sidecar = sidecar_path(out)
    run = _open_sidecar(sidecar, run_description(settings, seed, metadata_attrs), discard_partial)
    cell_model = factory()
    states_file = sidecar / "states.npz"
    if not states_file.exists():
        _save_npz(states_file, explore(cell_model, settings))
    missing = [c for c in range(n_chunks(settings)) if not _chunk_file(sidecar, c).exists()]
    todo = missing if max_chunks is None else missing[:max_chunks]
    done = settings.samples - sum(chunk_samples(settings, c) for c in missing)
    with tqdm(total=settings.samples, initial=done, desc="probes", unit="sample", smoothing=0.1) as bar:
        _compute_chunks(factory, cell_model, states_file, settings, seed, todo, workers, bar)
    if len(todo) < len(missing):
        return None
    _assemble(out, sidecar, settings, seed, run, metadata_attrs, clean)
    shutil.rmtree(sidecar)
    return out


# -- command line (composition root) ----------------------------------------------------
def _mesostructure_description(meso) -> dict[str, Any]:
    """JSON-ready description of a ``warp_hcell.mesostructure.Mesostructure``."""
    fields = ("radius", "position", "driven", "pairs", "outer", "cell_size", "pair_type")
    return {"name": meso.name, **{name: np.asarray(getattr(meso, name)).tolist() for name in fields}}


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m warp_hcell.generate`` argument parser (defaults from ``DatabaseSettings``)."""
    defaults = DatabaseSettings()
    parser = argparse.ArgumentParser(
        prog="python -m warp_hcell.generate", parents=[common_parser()],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Generate the meso-ANN learning database (docs/database_format.md): proportional "
                    "exploration paths, then seeded strain probes of the sampled states.")
    parser.add_argument("--out", type=Path, required=True, help="database file (HDF5) to write")
    parser.add_argument("--samples", type=positive_int, default=defaults.samples, help="number of samples")
    parser.add_argument("--backend", choices=GENERATOR_BACKENDS, default=GENERATOR_BACKENDS[0],
                        help="cell backend that explores and probes")
    parser.add_argument("--mesostructure", type=Path, default=None,
                        help="DEM mesostructure file (TOML/JSON, H-cell labels required); unset: the H-cell")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="worker processes computing chunks (the result does not depend on it)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="DEM CPU threads per process; unset: the DEM backend's own default")
    parser.add_argument("--chunk-size", type=positive_int, default=defaults.chunk_size,
                        help="probes per batch (unit of resume and of parallel work)")
    parser.add_argument("--max-chunks", type=positive_int, default=None,
                        help="compute at most this many chunks, then stop (rerun to resume)")
    parser.add_argument("--sample-spacing", type=positive_float, default=defaults.sample_spacing,
                        help="path length between sampled states along the exploration paths [-]")
    parser.add_argument("--n-directions", type=positive_int, default=defaults.n_directions,
                        help="proportional-leg directions in the (eps_n, eps_t) plane")
    parser.add_argument("--n-alpha0", type=positive_int, default=defaults.n_alpha0,
                        help="initial opening angles evenly spaced in [30, 89] deg (plus 35, 40, 55)")
    parser.add_argument("--clean", action="store_true", help="apply the cleaning step (warp_hcell.clean) to `valid`")
    return parser


def _run(argv: Sequence[str] | None) -> int:
    from homogenization.backends import make_cell_model  # noqa: PLC0415 (composition root)

    from warp_hcell.mesostructure import load_mesostructure  # noqa: PLC0415
    from warp_hcell.parameters import CellDefaults, ContactLaw, DemSettings  # noqa: PLC0415

    args = build_parser().parse_args(argv)
    settings = DatabaseSettings(samples=args.samples, chunk_size=args.chunk_size, sample_spacing=args.sample_spacing,
                                n_directions=args.n_directions, n_alpha0=args.n_alpha0)
    check_output_path(args.out, overwrite=args.overwrite)
    if args.out.is_dir():
        raise UserError(f"{args.out} is a folder; --out must be a file")
    law, radius = ContactLaw(), CellDefaults.radius
    meta: dict[str, Any] = {"backend": args.backend, "kn": law.kn, "kt": law.kt, "kt_over_kn": law.kt_over_kn,
                            "phi_g_deg": law.phi_g_deg, "radius": radius, "device": args.device}
    options: dict[str, Any] = {}
    if args.backend == "dem":
        meso = None
        if args.mesostructure is not None:
            if not args.mesostructure.is_file():
                raise UserError(f"mesostructure file {args.mesostructure} does not exist")
            meso = load_mesostructure(args.mesostructure)
            if not meso.is_h_cell:
                raise UserError(f"mesostructure {meso.name!r} has no H-cell labels (type1/type2): "
                                f"the database needs alpha, N1, N2, T1")
        options = {"mesostructure": meso, "settings": DemSettings(), "device": args.device}
        if args.threads is not None:
            options["threads"] = args.threads
        meta["dem_settings"] = asdict(DemSettings())
        meta["mesostructure"] = (_mesostructure_description(meso) if meso is not None else
                                 {"name": "h-cell", "builder": "warp_hcell.mesostructure.h_cell(alpha0_deg, radius)"})
    elif args.mesostructure is not None:
        raise UserError("--mesostructure needs --backend dem")
    factory = functools.partial(make_cell_model, args.backend, contact_law=law, radius=radius, **options)
    if options.get("mesostructure") is not None:
        # every path starts from the file's cell: the alpha0 grid is its opening angle
        cell_model = factory()
        alpha0 = float(cell_model.observables(cell_model.init_state(CellDefaults.alpha0_deg, 1))["alpha_deg"][0])
        settings = replace(settings, alpha0_min_deg=alpha0, alpha0_max_deg=alpha0, n_alpha0=1, alpha0_focus_deg=())
    start = time.perf_counter()
    written = generate(factory, settings, args.out, seed=args.seed, metadata_attrs=meta, workers=args.workers,
                       clean=args.clean, max_chunks=args.max_chunks, discard_partial=args.overwrite)
    elapsed = time.perf_counter() - start
    if written is None:
        print(f"stopped after --max-chunks {args.max_chunks} ({elapsed:.1f} s); rerun the same command to resume")
    else:
        print(f"{written}: {settings.samples} samples in {elapsed:.1f} s ({settings.samples / elapsed:.0f} samples/s)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point; bad input is one line on stderr and exit code 2."""
    return run_main(_run, argv)


if __name__ == "__main__":
    sys.exit(main())
