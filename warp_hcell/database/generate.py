"""Generates the generic learning database of the meso-ANN for any mesostructure (file format in
docs/database_format.md, written by ``warp_hcell.database.format``); the DEM
(``warp_hcell.dem.cell.DemCell``) explores and probes. ``--mesostructure`` takes a file or a
builder spec (``warp_hcell.mesostructures.builders``; the database records the hash of the cell,
name = spec text); without it the cell is ``hcell.h_cell`` and the exploration starts from
H-cells of several opening angles (``hcell.StartCells``).

The generator's jobs, one module each:

1. exploration (``warp_hcell.database.exploration``, deterministic): isotropic paths then
   proportional legs in the local strain space from every start cell; generic stop rules;
2. probing (``warp_hcell.database.probing``, seeded): a chunk of samples is a pure function of
   (settings, mesostructure, seed, chunk index), computed as one DEM batch;
3. storage and resume (``warp_hcell.database.shards``): the sidecar ``<out>.parts`` keeps each
   piece as soon as done; an interrupted run resumes where it stopped; a lock keeps a second
   run off the same ``--out``;
4. execution (``warp_hcell.core.execution``, injected): the tasks (``warp_hcell.database.tasks``)
   run in this process or on Dask (``--workers N``, ``--scheduler ADDRESS``); this process
   writes the results, so the file is bit-identical for a seed whatever the execution.

This module composes them: ``generate`` (the command is ``python -m warp_hcell.generate``). Cleaning is an explicit step
(``--clean`` here, or ``python -m warp_hcell.clean``): it marks unconverged and non-finite
samples.

Nothing in ``warp_hcell`` imports ``homogenization`` or ``training``. Sign convention:
compression and contraction positive; local frame index 0 = n, 1 = t (3D: 1 = t1, 2 = t2).
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from warp_hcell.database import clean as cleaning
from warp_hcell.database import format as database
from warp_hcell.core.files import output_lock
from warp_hcell.core.execution import InProcess, make_execution
from warp_hcell.database.exploration import DEM_PREFIX, UnreachableLevel, WalkProgress, turn_candidates
from warp_hcell.database.learning_state import free_coordinates
from warp_hcell.mesostructures.mesostructure import Mesostructure, shares_state_schema
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings, DemSettings, require_linear_law
from warp_hcell.database.probing import chunk_samples, FLOAT32_FEATURES, n_chunks
from warp_hcell.core.provenance import provenance
from warp_hcell.database.shards import DiskFull, Sidecar, sidecar_path
from warp_hcell.database.tasks import explore_starts, ExploreInputs, Physics, probe_chunk, ProbeInputs

__all__ = ["generate", "sidecar_path", "check_starts", "check_increments"]


def check_starts(meso: Mesostructure, starts: Sequence[Mesostructure]) -> None:
    """Raise ValueError (one line) unless every start cell is a state of ``meso``'s schema."""
    for start in starts:
        if not shares_state_schema(meso, start):
            raise ValueError(f"start cell {start.name!r} does not share the learning state of {meso.name!r}")


def check_increments(settings: DatabaseSettings, dem_settings: DemSettings) -> None:
    """Raise ValueError (one line) when an exploration increment or a probe needs more DEM
    substeps than ``max_substeps`` allows."""
    largest = max(settings.sample_spacing, settings.probe_max)
    finest = dem_settings.from_rest.refined_strain_per_substep
    if math.ceil(largest / finest) > dem_settings.max_substeps:
        raise ValueError(f"increment {largest:g} needs more substeps than max_substeps = {dem_settings.max_substeps} "
                         f"at {finest:g} per substep")


def run_description(meso: Mesostructure, starts: Sequence[Mesostructure], settings: DatabaseSettings, seed: int,
                    contact_law: ContactLaw, dem_settings: DemSettings) -> dict[str, Any]:
    """What identifies a run (resuming requires the same), JSON-ready."""
    return json.loads(json.dumps({
        "mesostructure": describe(meso), "starts": [describe(s) for s in starts], "generator": asdict(settings),
        "seed": int(seed), "dem_settings": asdict(dem_settings),
        "contact_law": {"kn": contact_law.kn, "kt": contact_law.kt, "kt_over_kn": contact_law.kt_over_kn,
                        "mu": contact_law.mu, "phi_g_deg": contact_law.phi_g_deg}}))


# -- the jobs, composed ------------------------------------------------------------------------
def _explore(execution, sidecar: Sidecar, inputs: ExploreInputs) -> dict[str, np.ndarray]:
    """The exploration states of every start cell, checkpointed per start cell in the sidecar.

    In process, the missing start cells are explored as one batch (the DEM threads share
    it); on Dask, one task per start cell. The states do not depend on the grouping.
    """
    n_starts = len(inputs.starts)
    parts = {k: sidecar.load(sidecar.file("start", k)) for k in range(n_starts)}
    missing = [k for k, part in parts.items() if part is None]
    groups = [tuple(missing)] if isinstance(execution, InProcess) else [(k,) for k in missing]
    for _, states in execution.map(explore_starts, inputs, [group for group in groups if group]):
        for k in np.unique(states["start_id"]):
            mine = states["start_id"] == k
            parts[int(k)] = {name: value[mine] for name, value in states.items()}
            sidecar.save(sidecar.file("start", int(k)), parts[int(k)])
    return {name: np.concatenate([parts[k][name] for k in range(n_starts)]) for name in parts[0]}


def _chunk_check(settings: DatabaseSettings, chunk: int, dim: int):
    n = chunk_samples(settings, chunk)
    return lambda arrays: "d_eps" in arrays and arrays["d_eps"].shape == (n, dim)


def _assemble(out: Path, states: Mapping[str, np.ndarray], chunks: Sequence[Mapping[str, np.ndarray]],
              meso: Mesostructure, settings: DatabaseSettings, run: Mapping[str, Any],
              description: Mapping[str, Any], clean: bool) -> None:
    """Write the database to a temporary file and rename it onto ``out``."""
    first = np.unique(states["start_id"], return_index=True)[1]
    stops = {name.split(".", 1)[1]: int(value[first].sum()) for name, value in states.items()
             if name.startswith("stops.")}
    data = {name: np.concatenate([part[name] for part in chunks]) for name in chunks[0]}
    schema = meso.schema()
    data.update(database.schema_datasets(schema))
    position = states[DEM_PREFIX + "position"]
    data.update({"states/cell_size": states[DEM_PREFIX + "cell_size"],
                 "states/free_position": free_coordinates(schema, position),
                 "states/shear_force": states[DEM_PREFIX + "shear_force"]})
    for name in ("path_id", "start_id", "precompression", "direction_deg", "turn_deg", "eps", *meso.parameters):
        if name in states:
            data[f"states/{name}"] = states[name]
    meso_text = description["mesostructure"]
    attrs = {
        "format": database.FORMAT,
        "format_version": database.FORMAT_VERSION,
        "sign_convention": database.SIGN_CONVENTION,
        "mesostructure": meso_text,
        "mesostructure_sha256": description_sha256(meso_text),
        "start_mesostructures": json.dumps(description["starts"]),
        "start_sha256": json.dumps([description_sha256(text) for text in description["starts"]]),
        **description["contact_law"],
        "dem_settings": description["dem_settings"],
        "seed": int(description["seed"]),
        "generator": description["generator"],
        "provenance": run["provenance"],
        "n_samples": int(settings.samples),
        "n_states": int(states["path_id"].size),
        "n_paths": int(np.unique(states["path_id"]).size),
        "n_unconverged": int(np.count_nonzero(~data["converged"])),
        "n_mechanism": int(np.count_nonzero(data["mechanism"])),
        "n_perturbed": int(np.count_nonzero(data["perturbed"])),
        "n_zero_probes": int(np.count_nonzero(np.all(data["d_eps"] == 0.0, axis=1))),
        "float32_datasets": json.dumps([f"{group}/{name}" for group in database.STATE_GROUPS for name in FLOAT32_FEATURES]),
        "exploration_stops": stops,
    }
    data["valid"], cleaning_attrs = cleaning.clean_samples(data) if clean else cleaning.not_cleaned(data)
    attrs.update(cleaning_attrs)
    try:
        database.write_database(out, data, attrs, database.dataset_attrs(schema, meso))
    except OSError as exc:  # h5py reports a full disk in its message, not always in errno
        if exc.errno == errno.ENOSPC or "No space left" in str(exc):
            raise DiskFull(errno.ENOSPC, "no space left on device", str(out)) from None
        raise


def generate(
    meso: Mesostructure,
    settings: DatabaseSettings,
    out: Path,
    *,
    seed: int,
    starts: Sequence[Mesostructure] | None = None,
    contact_law: ContactLaw = ContactLaw(),
    dem_settings: DemSettings = DemSettings(),
    device: str = "cpu",
    threads: int = 2,
    execution=None,
    workers: int = 1,
    clean: bool = False,
    max_chunks: int | None = None,
    discard_partial: bool = False,
    progress: Callable[[int, int], None] | None = None,
    explore_progress: WalkProgress | None = None,
) -> Path | None:
    """Generate (or resume) the database of ``meso`` into ``out`` (replaced atomically).

    Args:
        meso: the mesostructure (its learning state: the schema).
        settings, seed: generator settings; seed of the probes and state order.
        starts: start cells (same learning state); None = ``[meso]``.
        contact_law, dem_settings, device: the DEM's physics and numerics.
        threads, workers, execution: DEM threads, worker processes, where tasks run (not the result).
        clean: apply ``warp_hcell.clean`` first.
        max_chunks: at most this many new chunks, then return None.
        discard_partial: drop an unfinished run of other options.
        progress: called ``(samples probed, settings.samples)`` as probing starts and after
            each chunk; None: silent.
        explore_progress: wraps each exploration walk's loop (``Explorer``; picklable); None: silent.

    Returns:
        ``out`` once written, or None when stopped by ``max_chunks``.

    Raises:
        ValueError: a start of another learning state, an increment beyond max_substeps, an empty
            ``reversal_arc``, a non-linear law, an unfinished run of other options.
        UserError: another run writes ``out``. DiskFull: no space left."""
    require_linear_law(contact_law, "the learning database (its format stores kn, kt and phi_g; the meso-ANN "
                                    "learns from it)")
    starts = [meso] if starts is None else list(starts)
    check_starts(meso, starts)
    check_increments(settings, dem_settings)
    turn_candidates(settings)  # the turns' arc holds a sampled state (else ValueError, before any work)
    out = Path(out)
    description = run_description(meso, starts, settings, seed, contact_law, dem_settings)
    physics = Physics(contact_law, description["mesostructure"], dem_settings, str(device), int(threads))
    with output_lock(out):
        own = execution is None
        execution = make_execution(workers) if own else execution
        try:
            return _generate(execution, physics, meso, settings, out, description, seed, clean, max_chunks,
                             discard_partial, progress, explore_progress)
        finally:
            if own:
                execution.close()


def _silent(done: int, total: int) -> None:
    """The progress callback that reports nothing."""


def _generate(execution, physics: Physics, meso: Mesostructure, settings: DatabaseSettings, out: Path,
              description: Mapping[str, Any], seed: int, clean: bool, max_chunks: int | None,
              discard_partial: bool, progress: Callable[[int, int], None] | None,
              explore_progress: WalkProgress | None) -> Path | None:
    sidecar = Sidecar(out)
    run = sidecar.open(description, lambda: {k: v for k, v in provenance().items() if k != "command"},
                       discard_partial)
    states_file = sidecar.file("states")
    states = sidecar.load(states_file)
    if states is None:
        explore_inputs = ExploreInputs(physics, tuple(description["starts"]), settings, explore_progress)
        try:
            states = _explore(execution, sidecar, explore_inputs)
        except UnreachableLevel:
            if {p.name for p in sidecar.path.iterdir()} <= {"run.json"}:  # nothing computed: no sidecar left
                sidecar.remove()
            raise
        sidecar.save(states_file, states)
    chunks = {c: sidecar.load(sidecar.file("chunk", c), _chunk_check(settings, c, meso.dim))
              for c in range(n_chunks(settings))}
    missing = [c for c, part in chunks.items() if part is None]
    todo = missing if max_chunks is None else missing[:max_chunks]
    token = hashlib.sha256(json.dumps(description, sort_keys=True).encode()).hexdigest()[:16]
    inputs = ProbeInputs(token, physics, settings, int(seed), states)
    done = settings.samples - sum(chunk_samples(settings, c) for c in missing)
    report = progress or _silent
    report(done, settings.samples)
    for chunk, arrays in execution.map(probe_chunk, inputs, todo):
        sidecar.save(sidecar.file("chunk", chunk), arrays)
        chunks[chunk] = arrays
        done += chunk_samples(settings, chunk)
        report(done, settings.samples)
    if len(todo) < len(missing):
        return None
    _assemble(out, states, [chunks[c] for c in range(n_chunks(settings))], meso, settings, run, description, clean)
    sidecar.remove()
    return out
