"""Exploration tree of the database generator: the cell states that the probes start from.

Deterministic (no randomness). From each start cell (a batch of cells sharing one learning
state, ``warp_hcell.mesostructures.mesostructure.shares_state_schema``), one isotropic path compresses the
cell (d_eps_n = d_eps_t) through the precompression levels; from the state at each level,
proportional legs leave in ``n_directions`` directions psi of the (eps_n, eps_t) plane (all
directions: cells close, open, slide and lose contacts). A leg runs until its path length
reaches ``leg_length`` or its volumetric strain change reaches ``leg_volumetric``. All
active paths advance as ONE batch per increment and every state reached is sampled. The
increment is ``sample_spacing`` (path length), except at the start of a leg where it starts
at sample_spacing / 2**leg_refinement and doubles (finer sampling after the change of
direction, where the response changes fastest).

Stop rules (generic; ``stop_masks``): a path stops, and its state is not sampled, when the
DEM did not converge, a value is not finite, the cell has carried no contact force over a
path length above ``stress_free_length`` (open or force-free mechanism for long; shorter
force-free stretches are kept: the network must learn mechanisms), an overlap exceeds
``max_overlap`` (r_i + r_j), or ``|eps_n|`` or ``|eps_t|`` from the start cell exceeds
``max_cell_strain``. "No contact force" means every normal force <= the DEM's force floor
kn * contact_tolerance * mean grain diameter.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from warp_hcell.core.contract import StateSchema
from warp_hcell.core.cli import progress_bar
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings

DEM_PREFIX = "dem/"
"""Prefix of the DEM state arrays (``DemCell.state_to_arrays``) among the sampled-state arrays."""
STOP_RULES = {
    "unconverged": "the DEM did not reach equilibrium within max_substeps",
    "non_finite": "a non-finite value in the state",
    "stress_free": "no contact force over a path length > stress_free_length",
    "overlap": "an overlap > max_overlap (r_i + r_j)",
    "cell_strain": "|eps_n| or |eps_t| from the start cell > max_cell_strain",
}
"""Stop rules of the exploration and what they test."""


def leg_directions(settings: DatabaseSettings) -> np.ndarray:
    """Unit directions (d_eps_n, d_eps_t) of the legs, psi_k = 2 pi k / n, shape (n, 2)."""
    psi = 2.0 * np.pi * np.arange(settings.n_directions) / settings.n_directions
    return np.stack([np.cos(psi), np.sin(psi)], axis=1)


def leg_arc(settings: DatabaseSettings) -> np.ndarray:
    """Path length [-] of a leg after each of its increments, shape (K,), increasing.

    The first increment is sample_spacing / 2**leg_refinement; increments then double up to
    sample_spacing and stay there until leg_length.
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


def force_floor(schema: StateSchema, contact_law: ContactLaw, contact_tolerance: float) -> float:
    """Normal force [N] at or below which a cell counts as force-free: the DEM's force floor
    kn * contact_tolerance * mean grain diameter."""
    return contact_law.kn * contact_tolerance * 2.0 * float(schema.radius.mean())


def stop_masks(schema: StateSchema, arrays: Mapping[str, np.ndarray], eps: np.ndarray, stress_free_run: np.ndarray,
               settings: DatabaseSettings, contact_law: ContactLaw, contact_tolerance: float) -> dict[str, np.ndarray]:
    """Per-rule masks of the states where a path stops (``STOP_RULES``), each (n,) bool.

    Args:
        arrays: DEM state arrays (``DemCell.state_to_arrays``), first axis n.
        eps: (eps_n, eps_t) summed from the start cell [-], shape (n, 2).
        stress_free_run: path length over which the cell has carried no contact force,
            this state included [-], shape (n,).
    """
    position = np.asarray(arrays["position"])
    finite = np.ones(position.shape[0], dtype=bool)
    for name in ("position", "velocity", "shear_force", "cell_size"):
        value = np.asarray(arrays[name])
        finite &= np.isfinite(value.reshape(value.shape[0], -1)).all(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        ev = evaluate(schema, arrays["cell_size"], free_coordinates(schema, position), arrays["shear_force"],
                      contact_law, contact_tolerance)
        rsum = schema.radius[schema.pairs[:, 0]] + schema.radius[schema.pairs[:, 1]]
        overlap = (ev["normal_force"] / (contact_law.kn * rsum)).max(axis=1)
        return {
            "unconverged": np.asarray(arrays["converged"]) != 1,
            "non_finite": ~finite,
            "stress_free": stress_free_run > settings.stress_free_length * (1.0 + 1e-12),
            "overlap": ~(overlap <= settings.max_overlap) & finite,
            "cell_strain": ~(np.abs(eps).max(axis=1) <= settings.max_cell_strain) & finite,
        }


def stress_free(schema: StateSchema, arrays: Mapping[str, np.ndarray], contact_law: ContactLaw,
                contact_tolerance: float) -> np.ndarray:
    """True where every normal force of the DEM state is <= ``force_floor``, shape (n,)."""
    ev = evaluate(schema, arrays["cell_size"], free_coordinates(schema, np.asarray(arrays["position"])),
                  arrays["shear_force"], contact_law, contact_tolerance)
    return ev["normal_force"].max(axis=1) <= force_floor(schema, contact_law, contact_tolerance)


class Explorer:
    """Walks batches of DEM cells along their paths (module docstring).

    Args:
        cell_model: a ``warp_hcell.dem.cell.DemCell`` (any object with ``step``, ``take``,
            ``state_to_arrays``).
        schema: the learning state of the cells.
        settings: generator settings.
        contact_law, contact_tolerance: the DEM's (for the force-free and overlap rules).
    """

    def __init__(self, cell_model, schema: StateSchema, settings: DatabaseSettings, contact_law: ContactLaw,
                 contact_tolerance: float, n_starts: int = 1):
        self.cell_model = cell_model
        self.schema = schema
        self.settings = settings
        self.contact_law = contact_law
        self.contact_tolerance = contact_tolerance
        self.stops = {rule: np.zeros(n_starts, np.int64) for rule in STOP_RULES}
        """How often each stop rule fired, per start cell."""

    def _free_run(self, arrays, previous: np.ndarray, length: np.ndarray) -> np.ndarray:
        free = stress_free(self.schema, arrays, self.contact_law, self.contact_tolerance)
        return np.where(free, previous + length, 0.0)

    def walk(self, state, increments: np.ndarray, n_steps: np.ndarray, eps_start: np.ndarray,
             free_run_start: np.ndarray, cell_start: np.ndarray, label: str, *,
             sample_start: bool) -> dict[str, np.ndarray]:
        """Advance cells along their own increments, one batch per increment, sampling each state.

        Args:
            state: the start states, n_cells cells (admissible: start cells or sampled states).
            increments: (d_eps_n, d_eps_t) [-] of increment k of cell i, shape (n_cells, K, 2)
                (a broadcast view is fine), compression positive.
            n_steps: increments allowed per cell, shape (n_cells,) int, <= K.
            eps_start: (eps_n, eps_t) of the start states from their start cell, (n_cells, 2).
            free_run_start: force-free path length of the start states, (n_cells,).
            cell_start: start cell (0..n_starts-1) of each walked cell, (n_cells,) int.
            label: progress-bar label.
            sample_start: also sample the start states (step 0).

        Returns:
            The sampled states: ``cell`` (walk index) and ``step`` (increments done) int64,
            ``eps`` (n, 2), ``free_run`` (n,), and the DEM arrays prefixed ``DEM_PREFIX``.
        """
        cm = self.cell_model
        active = np.arange(increments.shape[0])
        eps, free_run = np.array(eps_start, dtype=np.float64), np.array(free_run_start, dtype=np.float64)
        parts = [self._record(cm.state_to_arrays(state), active, 0, eps, free_run)] if sample_start else []
        for k in progress_bar(range(int(n_steps.max(initial=0))), desc=label, unit="increment", leave=False):
            going = np.flatnonzero(n_steps[active] > k)
            if going.size < active.size:
                state, active, eps, free_run = cm.take(state, going), active[going], eps[going], free_run[going]
            if not active.size:
                break
            d_eps = np.ascontiguousarray(increments[active, k])
            state, _ = cm.step(state, d_eps)
            arrays = cm.state_to_arrays(state)
            eps = eps + d_eps
            free_run = self._free_run(arrays, free_run, np.hypot(d_eps[:, 0], d_eps[:, 1]))
            masks = stop_masks(self.schema, arrays, eps, free_run, self.settings, self.contact_law,
                               self.contact_tolerance)
            stop = np.zeros(active.size, dtype=bool)
            for rule, mask in masks.items():
                np.add.at(self.stops[rule], cell_start[active[mask & ~stop]], 1)
                stop |= mask
            keep = np.flatnonzero(~stop)
            state, active, eps, free_run = cm.take(state, keep), active[keep], eps[keep], free_run[keep]
            parts.append(self._record({name: value[keep] for name, value in arrays.items()}, active, k + 1, eps,
                                      free_run))
        return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}

    @staticmethod
    def _record(arrays: Mapping[str, np.ndarray], active: np.ndarray, step: int, eps: np.ndarray,
                free_run: np.ndarray) -> dict[str, np.ndarray]:
        record = {"cell": active, "step": np.full(active.size, step, np.int64), "eps": eps, "free_run": free_run}
        record.update({DEM_PREFIX + name: np.array(value) for name, value in arrays.items()})
        return record


def path_stride(settings: DatabaseSettings) -> int:
    """Path ids of start cell k are k * path_stride + (0: its isotropic path; 1, 2, ...: its legs)."""
    return 1 + len(set(settings.precompression)) * settings.n_directions


def explore(cell_model, start_state, schema: StateSchema, settings: DatabaseSettings, contact_law: ContactLaw,
            contact_tolerance: float, start_ids: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Run the exploration tree (module docstring) and return the sampled states.

    Args:
        cell_model: a ``DemCell``.
        start_state: the start cells (n_starts cells), touching and force-free.
        schema: their learning state.
        settings: generator settings.
        contact_law, contact_tolerance: the DEM's.
        start_ids: global index of each start cell, shape (n_starts,) int; default 0, 1, ...

    Returns:
        (states, stops): states with first axis n_states, ordered by start cell (then as
        walked), so that exploring the start cells together or apart gives the same states:
        the DEM arrays (prefix ``DEM_PREFIX``), ``path_id`` (``path_stride``) and ``start_id``
        int64, ``precompression`` [-] (isotropic strain the leg started from; the current one
        on isotropic paths), ``direction_deg`` [deg] (leg direction psi; NaN on isotropic
        paths), ``eps`` (n_states, 2) [-] summed from the start cell. ``stops``: rule ->
        how often it fired, per start cell, shape (n_starts,) int64.
    """
    n_starts = int(start_state.n_cells)
    explorer = Explorer(cell_model, schema, settings, contact_law, contact_tolerance, n_starts)
    start_ids = np.arange(n_starts, dtype=np.int64) if start_ids is None else np.asarray(start_ids, np.int64)
    stride = path_stride(settings)
    levels = np.unique(np.asarray(settings.precompression, dtype=np.float64))
    iso_strain = np.union1d(levels, np.arange(0.0, levels[-1], settings.sample_spacing / math.sqrt(2.0)))
    iso_increments = np.repeat(np.diff(iso_strain)[None, :, None], 2, axis=2)
    iso = explorer.walk(start_state, np.broadcast_to(iso_increments, (n_starts, *iso_increments.shape[1:])),
                        np.full(n_starts, iso_increments.shape[1]), np.zeros((n_starts, 2)),
                        np.zeros(n_starts), np.arange(n_starts), "isotropic paths", sample_start=True)
    iso_eps = iso_strain[iso.pop("step")]
    cell = iso["cell"]
    iso.update(path_id=start_ids[cell] * stride, start_id=start_ids[cell], precompression=iso_eps,
               direction_deg=np.full(iso_eps.size, np.nan))

    origin = np.flatnonzero(np.isin(iso_eps, levels))
    directions = leg_directions(settings)
    n_dir = directions.shape[0]
    leg_origin = np.repeat(origin, n_dir)
    leg_dir = np.tile(np.arange(n_dir), origin.size)
    arc = leg_arc(settings)
    steps = leg_steps(settings, directions, arc)[leg_dir]
    dem = {name[len(DEM_PREFIX):]: value[leg_origin] for name, value in iso.items() if name.startswith(DEM_PREFIX)}
    starts = cell_model.state_from_arrays(dem)
    increments = np.diff(arc, prepend=0.0)[None, :, None] * directions[leg_dir][:, None, :]
    legs = explorer.walk(starts, increments, steps, iso["eps"][leg_origin], iso["free_run"][leg_origin],
                         iso["cell"][leg_origin], "proportional legs", sample_start=False)
    legs.pop("step")
    cell = legs.pop("cell")
    start = leg_origin[cell]
    # leg number within its start cell, in creation order (whatever the other start cells)
    leg_start = iso["start_id"][leg_origin]
    by_start = np.argsort(leg_start, kind="stable")
    rank = np.empty(leg_start.size, np.int64)
    rank[by_start] = np.arange(leg_start.size) - np.searchsorted(leg_start[by_start], leg_start[by_start])
    legs.update(path_id=leg_start[cell] * stride + 1 + rank[cell], start_id=leg_start[cell],
                precompression=iso_eps[start], direction_deg=360.0 * leg_dir[cell] / n_dir)
    iso.pop("cell")
    states = {name: np.concatenate([iso[name], legs[name]]) for name in iso}
    states.pop("free_run")
    order = np.argsort(states["start_id"], kind="stable")
    return {name: value[order] for name, value in states.items()}, explorer.stops
