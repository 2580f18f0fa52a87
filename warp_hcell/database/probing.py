"""Probes of the database generator: one chunk of samples as a pure function of its inputs.

Sample i probes the sampled state ``order[i % n_states]`` (``order`` a seeded permutation,
so each state gets the same number of probes to within one) with an increment of uniform
direction in the local strain space ((d_eps_n, d_eps_t) in 2D, (d_eps_n, d_eps_t1, d_eps_t2) in
3D: the schema's ``dim``) and a log-uniform magnitude: with probability
``probe_focus_fraction`` in [probe_focus_min, probe_focus_max] (the increments the ANN is
mostly used with), otherwise in [probe_min, probe_max]. With probability
``perturbed_fraction`` the start state is perturbed: each free DOF moves by
amplitude x D x N(0, 1), amplitude log-uniform in [perturbation_min, perturbation_max]
(D the mean grain diameter), and a ``zero_probe_fraction`` of these probes is zero (the DEM
only relaxes the state).

Every start state is put in the canonical form of its learning state before the step:
driven DOFs at x_ref * l / l_ref of the schema's reference, velocities zero, tangential forces
after the contact-law evaluation (capped, zero out of contact); it is stepped from rest
(``DemCell.at_rest``: at ``DemSettings.rest_strain_per_substep``). The stored "before" state
therefore determines the DEM's "after" state exactly (with the probe and the schema).

``compute_chunk(context, settings, seed, chunk)`` depends on nothing else: chunk c draws
from streams (1, c) and (2, c) of the seed only, and a DEM cell's result does not depend on
its batch, so a database is bit-identical for a seed whatever the execution.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t
(3D: 1 = t1, 2 = t2).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from warp_hcell.core import libm
from warp_hcell.core.contract import StateSchema
from warp_hcell.database.dimensions import DIMENSIONS
from warp_hcell.database.exploration import DEM_PREFIX, force_floor
from warp_hcell.database.format import OBSERVABLES_GROUP
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.dem.love_weber import love_weber_tension_positive
from warp_hcell.mesostructures.mesostructure import Mesostructure, evaluate_observables, topology_arrays
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings

STATE_FEATURES = ("cell_size", "free_position", "shear_force", "contact", "normal_force", "unbalanced", "moment",
                  "area")
"""Datasets of the groups ``before`` and ``after`` (``StateSchema.features``)."""
FLOAT32_FEATURES = ("normal_force", "unbalanced", "moment")
"""Derived features stored in float32 (relative rounding 6e-8): each follows exactly from the
learning state (``cell_size``, ``free_position``, ``shear_force``, float64) and the contact law
(``learning_state.evaluate``), no replay or training reads them, and in float64 they took 39 %
of the default database of a ten-sphere cell with a fine grain (docs/database_format.md, "Size")."""


def rng(seed: int, *key: int) -> np.random.Generator:
    """Generator of stream ``key`` of ``seed`` (independent of any other stream)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def state_order(seed: int, n_states: int) -> np.ndarray:
    """Seeded permutation of the sampled states: sample i probes state ``order[i % n_states]``."""
    return rng(seed, 0).permutation(n_states)


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


def probe_increments(settings: DatabaseSettings, seed: int, chunk: int, n: int, dim: int = 2) -> np.ndarray:
    """Probes [-] of chunk ``chunk`` before zeroing, shape (n, dim): (d_eps_n, d_eps_t[, d_eps_t2]).

    Direction uniform: an angle in [0, 2 pi) in 2D, a normalised standard normal vector in 3D
    (drawn after the magnitudes); magnitude (Euclidean norm) log-uniform in
    [probe_focus_min, probe_focus_max] with probability ``probe_focus_fraction``, else in
    [probe_min, probe_max]. Drawn from stream (1, chunk) of ``seed`` only.
    """
    gen = rng(seed, 1, chunk)

    def magnitude() -> np.ndarray:
        focus = gen.random(n) < settings.probe_focus_fraction
        lo = np.where(focus, settings.probe_focus_min, settings.probe_min)
        hi = np.where(focus, settings.probe_focus_max, settings.probe_max)
        return libm.exp(libm.log(lo) + gen.random(n) * (libm.log(hi) - libm.log(lo)))

    return DIMENSIONS[dim].probes(gen, n, magnitude)


def perturbations(settings: DatabaseSettings, seed: int, chunk: int, n: int, n_free: int,
                  diameter: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Perturbation of the start states of chunk ``chunk`` (stream (2, chunk) of ``seed``).

    Returns:
        perturbed (n,) bool; zero_probe (n,) bool (only where perturbed); displacement
        (n, n_free) [m] of the free DOFs (zero where not perturbed).
    """
    gen = rng(seed, 2, chunk)
    perturbed = gen.random(n) < settings.perturbed_fraction
    zero_probe = perturbed & (gen.random(n) < settings.zero_probe_fraction)
    lo, hi = float(libm.log(settings.perturbation_min)), float(libm.log(settings.perturbation_max))
    amplitude = libm.exp(lo + gen.random(n) * (hi - lo)) * diameter
    direction = libm.standard_normal(gen, (n, n_free))
    return perturbed, zero_probe, np.where(perturbed[:, None], amplitude[:, None] * direction, 0.0)


@dataclass(frozen=True, eq=False)
class ProbeContext:
    """Everything a chunk needs besides (settings, seed, chunk index).

    Attributes:
        cell_model: a ``warp_hcell.dem.cell.DemCell`` of ``meso``.
        meso: the mesostructure (schema reference, declared observables and parameters).
        schema: ``meso.schema()``.
        states: the exploration's sampled states (``warp_hcell.database.exploration.explore``).
        contact_law, contact_tolerance: the DEM's.
    """

    cell_model: Any
    meso: Mesostructure
    schema: StateSchema
    states: Mapping[str, np.ndarray]
    contact_law: ContactLaw
    contact_tolerance: float

    @property
    def n_states(self) -> int:
        """Number of sampled states."""
        return int(self.states["path_id"].size)


def _features(ev: Mapping[str, np.ndarray], cell_size: np.ndarray, free_position: np.ndarray,
              prefix: str) -> dict[str, np.ndarray]:
    values = {"cell_size": np.array(cell_size, dtype=np.float64), "free_position": free_position,
              "shear_force": ev["shear_force"], "contact": ev["contact"], "normal_force": ev["normal_force"],
              "unbalanced": ev["unbalanced"], "moment": ev["moment"].reshape(ev["moment"].shape[0], -1),
              "area": ev["area"]}
    return {prefix + name: values[name].astype(np.float32) if name in FLOAT32_FEATURES else values[name]
            for name in STATE_FEATURES}


def canonical_dem_arrays(context: ProbeContext, ev: Mapping[str, np.ndarray], cell_size: np.ndarray) -> dict:
    """DEM state arrays of evaluated learning states (``learning_state.evaluate``), canonical form."""
    n = cell_size.shape[0]
    schema = context.schema
    branch = ev["position"][:, schema.pairs[:, 1]] - ev["position"][:, schema.pairs[:, 0]]
    return {
        "position": ev["position"], "velocity": np.zeros_like(ev["position"]), "shear_force": ev["shear_force"],
        "contact_force": ev["contact_force"], "contact": ev["contact"].astype(np.int32), "cell_size": cell_size,
        "moment": love_weber_tension_positive(ev["contact_force"], branch), "area": ev["area"],
        "substeps": np.zeros(n, np.int32), "converged": np.ones(n, np.int32),
        "radius": np.broadcast_to(schema.radius, (n, schema.n_grains)),
        "reference_position": np.broadcast_to(schema.reference_position, (n, schema.n_grains, schema.dim)),
        "reference_cell_size": np.broadcast_to(schema.reference_cell_size, (n, schema.dim)),
        **topology_arrays(context.meso, n),
    }


def step_from_rest(context: ProbeContext, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                   d_eps: np.ndarray, state_of: Callable[[dict], Any] | None = None
                   ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], Any]:
    """The DEM's increment of learning states from their canonical form (module docstring), one batch.

    Args:
        cell_size (n, dim) [m], free_position (n, n_free) [m], shear_force (n, ``*schema.shear_shape``) [N]:
            the learning states; d_eps (n, dim) [-]: the local strain increments, compression positive.
        state_of: builds the cell model's state from the canonical arrays (None: its ``state_from_arrays``;
            a caller that steps batches of one size again and again may keep their model).

    Returns:
        (the contact-law evaluation of the states, ``learning_state.evaluate``; the DEM's state arrays after
        the increment, ``cell_model.state_to_arrays``; its ``CellResponse``). Unconverged cells are flagged
        in the arrays' ``converged``, not warned about.
    """
    before = evaluate(context.schema, cell_size, free_position, shear_force, context.contact_law,
                      context.contact_tolerance)
    cm = context.cell_model
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        arrays = canonical_dem_arrays(context, before, cell_size)
        new, response = cm.step(cm.at_rest((state_of or cm.state_from_arrays)(arrays)), d_eps)
    return before, cm.state_to_arrays(new), response


def compute_chunk(context: ProbeContext, settings: DatabaseSettings, seed: int, chunk: int) -> dict[str, np.ndarray]:
    """All samples of one chunk, computed as ONE DEM batch (module docstring).

    Returns:
        Flat arrays, first axis the chunk's samples: ``before/<feature>``, ``after/<feature>``
        (``STATE_FEATURES``), ``d_eps`` (n, dim), ``mechanism``, ``perturbed``, ``converged``
        (bool), ``state_id``, ``path_id`` (int64), ``substeps`` (int64, DEM substeps of the
        probe), the declared observables ``<group>/before_<name>``, ``<group>/after_<name>``
        (``format.stored_observables``) and the start cell's parameters (``Mesostructure.parameters``).
    """
    schema, law, tol = context.schema, context.contact_law, context.contact_tolerance
    start, stop = chunk_bounds(settings, chunk)
    sample = np.arange(start, stop)
    n = sample.size
    index = state_order(seed, context.n_states)[sample % context.n_states]
    d_eps = probe_increments(settings, seed, chunk, n, schema.dim)
    perturbed, zero_probe, displacement = perturbations(settings, seed, chunk, n, schema.n_free,
                                                        2.0 * float(schema.radius.mean()))
    d_eps[zero_probe] = 0.0
    states = context.states
    cell_size = np.array(states[DEM_PREFIX + "cell_size"][index])
    free = free_coordinates(schema, states[DEM_PREFIX + "position"][index]) + displacement
    before, dem, _ = step_from_rest(context, cell_size, free, states[DEM_PREFIX + "shear_force"][index], d_eps)
    after_free = free_coordinates(schema, dem["position"])
    after = evaluate(schema, dem["cell_size"], after_free, dem["shear_force"], law, tol)
    out = {**_features(before, cell_size, free, "before/"), **_features(after, dem["cell_size"], after_free, "after/")}
    out.update({
        "d_eps": d_eps,
        "mechanism": before["normal_force"].max(axis=1) <= force_floor(schema, law, tol),
        "perturbed": perturbed,
        "converged": dem["converged"] == 1,
        "state_id": index.astype(np.int64),
        "path_id": states["path_id"][index].astype(np.int64),
        "substeps": dem["substeps"].astype(np.int64),
    })
    for name, ev in (("before", before), ("after", after)):
        obs = evaluate_observables(context.meso, ev["position"], ev["normal_force"], ev["shear_force"])
        out.update({f"{OBSERVABLES_GROUP}/{name}_{key}": value for key, value in obs.items()})
    for name in context.meso.parameters:
        out[name] = states[name][index]
    return out
