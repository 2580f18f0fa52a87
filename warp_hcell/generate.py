"""python -m warp_hcell.generate [--mesostructure FILE] --samples 300000 --seed 0 --out runs/db.h5

Generates the generic learning database of the meso-ANN for ANY mesostructure (file format
in docs/database_format.md, written by ``warp_hcell.database``). The DEM
(``warp_hcell.dem_cell.DemCell``) explores and probes; without ``--mesostructure`` the cell is
the H-cell of ``warp_hcell.mesostructure.h_cell`` and the exploration starts from H-cells of
several opening angles (they share one learning state).

Jobs:
1. Exploration (``warp_hcell.exploration``, deterministic): isotropic paths then proportional
   legs in the (eps_n, eps_t) plane from every start cell; generic stop rules.
2. Probing (``warp_hcell.probing``, seeded): each chunk of samples is a pure function of
   (settings, mesostructure, seed, chunk index), computed as ONE DEM batch.
3. Storage and resume (here): completed work goes to a sidecar folder ``<out>.parts``
   (``run.json``, ``states.npz`` = the exploration checkpoint, one ``chunk_XXXXXX.npz`` per
   chunk, each written to a temporary name and renamed), so an interrupted run resumes
   where it stopped. When all chunks exist, the HDF5 file is written to a temporary file
   and renamed onto ``--out``; the sidecar is then removed.
4. Execution (here): chunks run in this process or in ``--workers`` processes; the file is
   bit-identical for a seed whatever the workers and interruptions.
Cleaning is an explicit step (``--clean`` here, or ``python -m warp_hcell.clean``): it marks
unconverged and non-finite samples; mechanism and perturbed samples are kept.

Nothing in ``warp_hcell`` imports ``homogenization`` or ``training``.
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
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from warp_hcell import clean as cleaning
from warp_hcell import database
from warp_hcell.cli import UserError, check_output_path, common_parser, positive_float, positive_int, run_main
from warp_hcell.exploration import DEM_PREFIX, explore
from warp_hcell.learning_state import free_coordinates, hcell_observables
from warp_hcell.mesostructure import (
    Mesostructure, describe, description_sha256, from_description, h_cell, load_mesostructure, shares_state_schema)
from warp_hcell.parameters import CellDefaults, ContactLaw, DatabaseSettings, DemSettings
from warp_hcell.probing import ProbeContext, chunk_samples, compute_chunk, n_chunks
from warp_hcell.provenance import provenance


def h_cell_starts(settings: DatabaseSettings, radius: float = CellDefaults.radius) -> list[Mesostructure]:
    """H-cells at the opening angles of the settings (even grid plus focus angles), sorted."""
    grid = np.linspace(settings.alpha0_min_deg, settings.alpha0_max_deg, settings.n_alpha0)
    angles = np.unique(np.concatenate([grid, np.asarray(settings.alpha0_focus_deg, dtype=np.float64)]))
    return [h_cell(float(a), radius) for a in angles]


def check_starts(meso: Mesostructure, starts: Sequence[Mesostructure]) -> None:
    """Raise ValueError (one line) unless every start cell is a state of ``meso``'s schema."""
    for start in starts:
        if not shares_state_schema(meso, start):
            raise ValueError(f"start cell {start.name!r} does not share the learning state of {meso.name!r}")


def check_increments(settings: DatabaseSettings, dem_settings: DemSettings) -> None:
    """Raise ValueError (one line) when an exploration increment or a probe needs more DEM
    substeps than ``max_substeps`` allows."""
    largest = max(settings.sample_spacing, settings.probe_max)
    if math.ceil(largest / dem_settings.strain_per_substep) > dem_settings.max_substeps:
        raise ValueError(f"increment {largest:g} needs more substeps than max_substeps = {dem_settings.max_substeps} "
                         f"at {dem_settings.strain_per_substep:g} per substep")


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


def sidecar_path(out: Path) -> Path:
    """Folder holding the completed work of an unfinished run writing ``out``."""
    return out.with_name(out.name + ".parts")


def _chunk_file(sidecar: Path, chunk: int) -> Path:
    return sidecar / f"chunk_{chunk:06d}.npz"


def _open_sidecar(sidecar: Path, description: Mapping[str, Any], discard_partial: bool) -> dict[str, Any]:
    """Start or resume the run recorded in ``sidecar/run.json``; returns its record.

    The record keeps the provenance of the run's start (command line left out), so a
    resumed run writes the same attrs as an uninterrupted one.
    """
    run_file = sidecar / "run.json"
    if run_file.exists() and json.loads(run_file.read_text())["description"] != description:
        if not discard_partial:
            raise ValueError(f"{sidecar} holds an unfinished run with other options; "
                             f"rerun it with the same options or pass --overwrite to discard it")
        shutil.rmtree(sidecar)
    if not run_file.exists():
        sidecar.mkdir(parents=True, exist_ok=True)
        record = {key: value for key, value in provenance().items() if key != "command"}
        run = {"description": description, "provenance": record}
        tmp = run_file.with_name("run.json.tmp")
        tmp.write_text(json.dumps(run, indent=1, sort_keys=True))
        os.replace(tmp, run_file)
    return json.loads(run_file.read_text())


# -- execution -----------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _dem_cell(contact_law: ContactLaw, meso_text: str, dem_settings: DemSettings, device: str, threads: int):
    from warp_hcell.dem_cell import DemCell  # noqa: PLC0415 (Warp loads only where cells are stepped)

    return DemCell(contact_law, CellDefaults.radius, mesostructure=from_description(meso_text),
                   settings=dem_settings, device=device, threads=threads)


@functools.lru_cache(maxsize=1)
def _context(contact_law: ContactLaw, meso_text: str, dem_settings: DemSettings, device: str, threads: int,
             states_file: str, states_version: tuple[int, int]) -> ProbeContext:
    """The probe context of a run (built once per process; ``states_version`` = the states
    file's (mtime_ns, size), so a rewritten file is reloaded)."""
    meso = from_description(meso_text)
    return ProbeContext(cell_model=_dem_cell(contact_law, meso_text, dem_settings, device, threads), meso=meso,
                        schema=meso.schema(), states=_load_npz(Path(states_file)), contact_law=contact_law,
                        contact_tolerance=dem_settings.contact_tolerance)


def _run_chunk(physics: tuple, states_file: str, settings: DatabaseSettings, seed: int, chunk: int) -> int:
    """Compute chunk ``chunk``, save it to the sidecar, return its size (any process)."""
    stat = os.stat(states_file)
    arrays = compute_chunk(_context(*physics, states_file, (stat.st_mtime_ns, stat.st_size)), settings, seed, chunk)
    _save_npz(_chunk_file(Path(states_file).parent, chunk), arrays)
    return chunk_samples(settings, chunk)


def _compute_chunks(physics: tuple, states_file: Path, settings: DatabaseSettings, seed: int, todo: Sequence[int],
                    workers: int, bar: tqdm) -> None:
    """Compute chunks ``todo`` into the sidecar, in this process or in ``workers`` processes."""
    if workers <= 1 or len(todo) <= 1:
        for chunk in todo:
            bar.update(_run_chunk(physics, str(states_file), settings, seed, chunk))
        return
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as executor:
        jobs = [executor.submit(_run_chunk, physics, str(states_file), settings, seed, chunk) for chunk in todo]
        try:
            for job in jobs:
                bar.update(job.result())
        finally:
            for job in jobs:
                job.cancel()


# -- the run ---------------------------------------------------------------------------------
def _explore(physics: tuple, meso: Mesostructure, starts: Sequence[Mesostructure],
             settings: DatabaseSettings) -> dict[str, np.ndarray]:
    """Exploration states (``warp_hcell.exploration.explore``) plus ``stops.<rule>`` counts and,
    for H-cells, ``alpha0_deg`` of each state's start cell."""
    from warp_hcell.dem_cell import DemCellState  # noqa: PLC0415
    from warp_hcell.model import DemModel  # noqa: PLC0415

    contact_law, meso_text, dem_settings, device, _ = physics
    cell_model = _dem_cell(*physics)
    model = DemModel.build(list(starts), len(starts), contact_law=contact_law, settings=dem_settings, device=device)
    states, stops = explore(cell_model, DemCellState(model, model.state()), meso.schema(), settings, contact_law,
                            dem_settings.contact_tolerance)
    if meso.is_h_cell:
        start_alpha = np.array([hcell_observables(s, s.position[None], np.zeros((1, s.n_pairs)),
                                                  np.zeros((1, s.n_pairs)))["alpha_deg"][0] for s in starts])
        states["alpha0_deg"] = start_alpha[states["start_id"]]
    states.update({f"stops.{rule}": np.int64(count) for rule, count in stops.items()})
    return states


def _assemble(out: Path, sidecar: Path, meso: Mesostructure, settings: DatabaseSettings,
              run: Mapping[str, Any], description: Mapping[str, Any], clean: bool) -> None:
    """Write the database from the sidecar's chunks to a temporary file, rename it onto ``out``."""
    states = _load_npz(sidecar / "states.npz")
    stops = {name.split(".", 1)[1]: int(value) for name, value in states.items() if name.startswith("stops.")}
    chunks = [_load_npz(_chunk_file(sidecar, c)) for c in range(n_chunks(settings))]
    data = {name: np.concatenate([part[name] for part in chunks]) for name in chunks[0]}
    schema = meso.schema()
    data.update(database.schema_datasets(schema))
    position = states[DEM_PREFIX + "position"]
    data.update({"states/cell_size": states[DEM_PREFIX + "cell_size"],
                 "states/free_position": free_coordinates(schema, position),
                 "states/shear_force": states[DEM_PREFIX + "shear_force"]})
    for name in ("path_id", "start_id", "precompression", "direction_deg", "eps", "alpha0_deg"):
        if name in states:
            data[f"states/{name}"] = states[name]
    meso_text = description["mesostructure"]
    attrs = {
        "format": database.FORMAT,
        "format_version": database.FORMAT_VERSION,
        "sign_convention": database.SIGN_CONVENTION,
        "mesostructure": meso_text,
        "mesostructure_sha256": description_sha256(meso_text),
        "is_h_cell": bool(meso.is_h_cell),
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
        "exploration_stops": stops,
    }
    data["valid"], cleaning_attrs = cleaning.clean_samples(data) if clean else cleaning.not_cleaned(data)
    attrs.update(cleaning_attrs)
    database.write_database(out, data, attrs, database.dataset_attrs(schema, meso.is_h_cell))


def run_description(meso: Mesostructure, starts: Sequence[Mesostructure], settings: DatabaseSettings, seed: int,
                    contact_law: ContactLaw, dem_settings: DemSettings) -> dict[str, Any]:
    """What identifies a run (resuming requires the same), JSON-ready."""
    return json.loads(json.dumps({
        "mesostructure": describe(meso), "starts": [describe(s) for s in starts], "generator": asdict(settings),
        "seed": int(seed), "dem_settings": asdict(dem_settings),
        "contact_law": {"kn": contact_law.kn, "kt": contact_law.kt, "kt_over_kn": contact_law.kt_over_kn,
                        "mu": contact_law.mu, "phi_g_deg": contact_law.phi_g_deg}}))


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
    workers: int = 1,
    clean: bool = False,
    max_chunks: int | None = None,
    discard_partial: bool = False,
) -> Path | None:
    """Generate (or resume) the database of ``meso`` and write it to ``out``.

    Args:
        meso: the mesostructure (its learning state is the database's schema).
        settings: generator settings.
        out: database file to write (replaced atomically at the end).
        seed: seed of the probes, perturbations and state order.
        starts: start cells of the exploration, each sharing ``meso``'s learning state;
            None = ``[meso]``.
        contact_law, dem_settings, device: the DEM's physics and numerics.
        threads: DEM CPU threads per process (the result does not depend on it).
        workers: processes computing chunks in parallel (the result does not depend on it).
        clean: apply ``warp_hcell.clean`` before writing.
        max_chunks: compute at most this many new chunks, then return None without writing
            ``out`` (the run resumes later).
        discard_partial: drop an unfinished run of other options found in the sidecar
            instead of refusing.

    Returns:
        ``out`` once written, or None when stopped by ``max_chunks``.

    Raises:
        ValueError: (one line) a start cell of another learning state, or the sidecar holds
            an unfinished run with other options.
    """
    starts = [meso] if starts is None else list(starts)
    check_starts(meso, starts)
    check_increments(settings, dem_settings)
    out = Path(out)
    sidecar = sidecar_path(out)
    description = run_description(meso, starts, settings, seed, contact_law, dem_settings)
    run = _open_sidecar(sidecar, description, discard_partial)
    physics = (contact_law, description["mesostructure"], dem_settings, str(device), int(threads))
    states_file = sidecar / "states.npz"
    if not states_file.exists():  # the workers are idle meanwhile: the exploration uses their threads too
        _save_npz(states_file, _explore((*physics[:4], int(threads) * max(int(workers), 1)), meso, starts, settings))
    missing = [c for c in range(n_chunks(settings)) if not _chunk_file(sidecar, c).exists()]
    todo = missing if max_chunks is None else missing[:max_chunks]
    done = settings.samples - sum(chunk_samples(settings, c) for c in missing)
    with tqdm(total=settings.samples, initial=done, desc="probes", unit="sample", smoothing=0.1) as bar:
        _compute_chunks(physics, states_file, settings, seed, todo, workers, bar)
    if len(todo) < len(missing):
        return None
    _assemble(out, sidecar, meso, settings, run, description, clean)
    shutil.rmtree(sidecar)
    return out


# -- command line ------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The ``python -m warp_hcell.generate`` argument parser (defaults from ``DatabaseSettings``)."""
    defaults = DatabaseSettings()
    parser = argparse.ArgumentParser(
        prog="python -m warp_hcell.generate", parents=[common_parser()],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Generate the generic meso-ANN learning database of a mesostructure with the DEM "
                    "(docs/database_format.md): exploration paths, then seeded strain probes and perturbed "
                    "states of the sampled states.")
    parser.add_argument("--out", type=Path, required=True, help="database file (HDF5) to write")
    parser.add_argument("--mesostructure", type=Path, default=None,
                        help="mesostructure file (TOML/JSON, warp_hcell/data); unset: the H-cell, explored from "
                             "H-cells of several opening angles")
    parser.add_argument("--samples", type=positive_int, default=defaults.samples, help="number of samples")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="worker processes computing chunks (the result does not depend on it)")
    parser.add_argument("--threads", type=positive_int, default=2,
                        help="DEM CPU threads per process (the result does not depend on it)")
    parser.add_argument("--chunk-size", type=positive_int, default=defaults.chunk_size,
                        help="probes per batch (unit of resume and of parallel work)")
    parser.add_argument("--max-chunks", type=positive_int, default=None,
                        help="compute at most this many chunks, then stop (rerun to resume)")
    parser.add_argument("--sample-spacing", type=positive_float, default=defaults.sample_spacing,
                        help="path length between sampled states along the exploration paths [-]")
    parser.add_argument("--n-directions", type=positive_int, default=defaults.n_directions,
                        help="proportional-leg directions in the (eps_n, eps_t) plane")
    parser.add_argument("--n-alpha0", type=positive_int, default=defaults.n_alpha0,
                        help="default H-cell only: start cells at opening angles evenly spaced in [30, 89] deg "
                             "(plus 35, 40, 55)")
    parser.add_argument("--perturbed-fraction", type=float, default=defaults.perturbed_fraction,
                        help="fraction of probes starting from a perturbed (unbalanced) state")
    parser.add_argument("--clean", action="store_true",
                        help="apply the cleaning step (warp_hcell.clean: unconverged, non-finite) to `valid`")
    return parser


def _run(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    try:
        settings = DatabaseSettings(samples=args.samples, chunk_size=args.chunk_size,
                                    sample_spacing=args.sample_spacing, n_directions=args.n_directions,
                                    n_alpha0=args.n_alpha0, perturbed_fraction=args.perturbed_fraction)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_output_path(args.out, overwrite=args.overwrite)
    if args.out.is_dir():
        raise UserError(f"{args.out} is a folder; --out must be a file")
    if args.mesostructure is None:
        meso = h_cell(CellDefaults.alpha0_deg, CellDefaults.radius)
        starts = h_cell_starts(settings, CellDefaults.radius)
    else:
        if not args.mesostructure.is_file():
            raise UserError(f"mesostructure file {args.mesostructure} does not exist")
        meso = load_mesostructure(args.mesostructure)
        starts = [meso]
    start = time.perf_counter()
    written = generate(meso, settings, args.out, seed=args.seed, starts=starts, device=args.device,
                       threads=args.threads, workers=args.workers, clean=args.clean, max_chunks=args.max_chunks,
                       discard_partial=args.overwrite)
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
