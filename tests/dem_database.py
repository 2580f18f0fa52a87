"""Small generic learning databases (format version 2, GENERIC_DB_FORMAT / docs/database_format.md) made with DemCell.

Test helper: the ANN and training tests build their data with the DEM itself, in seconds.
States are sampled along proportional legs (after an isotropic precompression) in the
(eps_n, eps_t) plane; from each state one probe, and a share of the states are first
perturbed (free DOFs displaced at random, an unbalanced state the DEM relaxes during the probe).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import torch

from training import cell_physics
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import ContactLaw, DemSettings


def _schema(meso: Mesostructure, law: ContactLaw, settings: DemSettings) -> cell_physics.CellSchema:
    return cell_physics.CellSchema.from_arrays(
        radius=meso.radius, reference_position=meso.position, reference_cell_size=meso.cell_size,
        driven=meso.driven, pairs=meso.pairs, outer=meso.outer, kn=law.kn, kt=law.kt, mu=law.mu,
        contact_tolerance=settings.contact_tolerance)


def _generic(arrays: dict, meso: Mesostructure, schema: cell_physics.CellSchema) -> dict[str, np.ndarray]:
    """Generic state datasets of DEM state arrays (normal force, contact, unbalanced recomputed)."""
    free = np.argwhere(~meso.driven)
    size = torch.from_numpy(np.asarray(arrays["cell_size"], float))
    free_position = torch.from_numpy(arrays["position"][:, free[:, 0], free[:, 1]])
    shear = torch.from_numpy(np.asarray(arrays["shear_force"], float))
    x = cell_physics.positions(schema, size, free_position)
    c = cell_physics.contacts(schema, x)
    force = cell_physics.pair_forces(c, shear)
    return {"cell_size": size.numpy(), "free_position": free_position.numpy(),
            "shear_force": torch.where(c.contact, shear, 0.0).numpy(), "contact": c.contact.numpy().astype(np.int8),
            "normal_force": c.normal_force.numpy(),
            "unbalanced": cell_physics.unbalanced(schema, force, meso.n_grains).numpy()}


def build(out: Path, *, mesostructure: Mesostructure | None = None, alpha0_deg=(55.0,), radius: float = 0.5,
          precompression=(0.0, 1e-3, 1e-2), n_directions: int = 8, spacing: float = 1e-2, leg_length: float = 0.2,
          leg_volumetric: float = 0.05, perturbed_fraction: float = 0.4, perturbation=(1e-7, 1e-4),
          probe=(1e-6, 1e-3), probes_per_state: int = 1, seed: int = 0, law: ContactLaw = ContactLaw(),
          settings: DemSettings = DemSettings(), threads: int = 2) -> Path:
    """Write a generic database to ``out`` and return it.

    Without ``mesostructure`` the cells are H-cells from the builder at every ``alpha0_deg``
    (then ``alpha0_deg`` is stored per sample); with one, every path starts from it.
    Perturbations are Gaussian with a standard deviation log-uniform in ``perturbation`` [D];
    probe magnitudes are log-uniform in ``probe`` (a perturbed state gets a zero probe with
    probability 0.2). Every sampled state gets ``probes_per_state`` probes.
    """
    rng = np.random.default_rng(seed)
    dem = DemCell(law, radius, settings=settings, threads=threads)
    meso = mesostructure if mesostructure is not None else h_cell(alpha0_deg[0], radius)
    schema = _schema(meso, law, settings)
    diameter = schema.diameter
    alphas = np.asarray(alpha0_deg if mesostructure is None else (np.nan,), float)
    psi = 2 * np.pi * np.arange(n_directions) / n_directions
    grid = np.array([(a, e, p) for a in alphas for e in precompression for p in psi])
    n_paths = grid.shape[0]
    state = dem.init_state(mesostructure if mesostructure is not None else [h_cell(a, radius) for a in grid[:, 0]],
                           n_paths)
    state, _ = dem.step(state, np.repeat(grid[:, 1:2], 2, axis=1))
    direction = np.column_stack([np.cos(grid[:, 2]), np.sin(grid[:, 2])])
    volumetric = np.abs(direction.sum(axis=1))
    n_steps = np.minimum(leg_length, leg_volumetric / np.maximum(volumetric, 1e-12)) / spacing
    kept, path_of = [], []
    for k in range(int(np.ceil(n_steps.max()))):
        kept.append(state)
        path_of.append(np.flatnonzero(k < n_steps))
        state, _ = dem.step(state, spacing * direction * (k < n_steps)[:, None])
    # gather every sampled state into one batch
    batches = [dem.take(s, idx) for s, idx in zip(kept, path_of)]
    arrays = {k: np.concatenate([dem.state_to_arrays(b)[k] for b in batches]) for k in dem.state_to_arrays(batches[0])}
    repeat = np.repeat(np.arange(sum(i.size for i in path_of)), probes_per_state)
    arrays = {k: v[repeat] for k, v in arrays.items()}
    path_id = np.concatenate(path_of)[repeat]
    n = path_id.size
    perturbed = rng.random(n) < perturbed_fraction
    free = np.argwhere(~meso.driven)
    sigma = diameter * np.exp(rng.uniform(*np.log(perturbation), size=n))
    shift = rng.normal(size=(n, free.shape[0])) * sigma[:, None] * perturbed[:, None]
    arrays["position"][:, free[:, 0], free[:, 1]] += shift
    arrays["velocity"][:] = 0.0
    before_state = dem.state_from_arrays(arrays)
    magnitude = np.exp(rng.uniform(*np.log(probe), size=n)) * ~(perturbed & (rng.random(n) < 0.2))
    angle = rng.uniform(0, 2 * np.pi, n)
    d_eps = magnitude[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    after_state, _ = dem.step(before_state, d_eps)
    after_arrays = dem.state_to_arrays(after_state)
    before = _generic(arrays, meso, schema)
    after = _generic(after_arrays, meso, schema)
    text = describe(meso)
    starts = [text] if mesostructure is not None else [describe(h_cell(a, radius)) for a in alphas]
    out = Path(out)
    with h5py.File(out, "w") as f:
        f.attrs.update({"format": "meso-hmodel-database", "format_version": 2, "mesostructure": text,
                        "mesostructure_sha256": description_sha256(text),
                        "start_mesostructures": json.dumps(starts),
                        "start_sha256": json.dumps([description_sha256(t) for t in starts]), "kn": law.kn,
                        "kt": law.kt, "mu": law.mu, "phi_g_deg": law.phi_g_deg, "kt_over_kn": law.kt_over_kn,
                        "seed": seed, "n_samples": n,
                        "dem_settings": json.dumps({"contact_tolerance": settings.contact_tolerance})})
        s = f.create_group("schema")
        s["free_dofs"] = free.astype(np.int64)
        s["pairs"] = meso.pairs
        s["radius"] = meso.radius
        s["reference_position"] = meso.position
        s["reference_cell_size"] = meso.cell_size
        s["driven"] = meso.driven
        s["outer"] = meso.outer
        for name, group in (("before", before), ("after", after)):
            g = f.create_group(name)
            for key, value in group.items():
                g[key] = value
        f["d_eps"] = d_eps
        f["mechanism"] = ~(before["normal_force"] > 0).any(axis=1)
        f["perturbed"] = perturbed
        f["converged"] = after_arrays["converged"] == 1
        f["state_id"] = np.arange(n)
        f["path_id"] = path_id
        if mesostructure is None:
            f["alpha0_deg"] = grid[path_id, 0]
    return out
