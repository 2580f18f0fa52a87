"""Exploration tree of the database generator: the cell states that the probes start from.

Deterministic. From each start cell (a batch of cells sharing one learning state,
``warp_hcell.mesostructures.mesostructure.shares_state_schema``) one isotropic path compresses
the cell through the precompression levels; from each level, proportional legs leave in
``n_directions`` directions of the local strain space (``leg_directions``: angles psi of the
(eps_n, eps_t) plane in 2D, a spherical Fibonacci set in 3D). A leg runs until its path length
reaches ``leg_length`` or its volumetric strain change ``leg_volumetric``. All active paths
advance as one batch per increment and every state reached is sampled; the increment is
``sample_spacing``, refined by 2**leg_refinement at the start of a leg and doubling.

Turning branches (``reversal_legs`` per leg, ``turn_branches``): each leaves a sampled state of
its leg (at a path length drawn in ``reversal_arc``) in the leg's direction turned by > 90 deg
(negated for a fraction ``reversal_negated_fraction``, else by an angle drawn in
[``reversal_min_angle_deg``, 180] deg), and runs like a leg. The draws come from a generator
seeded with (``TURN_STREAM``, start id), so they depend neither on the generator's seed nor on
how start cells are grouped. A branch whose leg stopped before its turn is counted as
``turn_not_reached``.

Stop rules (``stop_masks``): a path stops, unsampled, when the DEM did not converge, a value is
not finite, the cell carried no contact force (every normal force <= kn * contact_tolerance *
mean diameter) over a path length above ``stress_free_length``, an overlap exceeds
``max_overlap`` (r_i + r_j), or a local strain component from the start cell exceeds
``max_cell_strain``. A path length is the Euclidean norm of the local strain increments.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t
(3D: 1 = t1, 2 = t2). Arrays of strains have ``dim`` columns.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from warp_hcell.core import libm
from warp_hcell.core.contract import StateSchema
from warp_hcell.database.dimensions import DIMENSIONS
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings

DEM_PREFIX = "dem/"
"""Prefix of the DEM state arrays (``DemCell.state_to_arrays``) among the sampled-state arrays."""
STOP_RULES = {
    "unconverged": "the DEM did not reach equilibrium within max_substeps",
    "non_finite": "a non-finite value in the state",
    "stress_free": "no contact force over a path length > stress_free_length",
    "overlap": "an overlap > max_overlap (r_i + r_j)",
    "cell_strain": "a local strain component from the start cell (|eps_n|, |eps_t|, ...) > max_cell_strain",
}
"""Stop rules of the exploration and what they test."""
TURN_NOT_REACHED = "turn_not_reached"
"""Stop-count key of the turning branches not walked because their leg stopped before the turn."""
TURN_STREAM = 0x7475726E
"""First word of the seed of the turning branches' draws (then the start id)."""


class UnreachableLevel(ValueError):
    """A precompression level that no start cell reaches on its isotropic path (one line)."""


def leg_directions(settings: DatabaseSettings, dim: int = 2) -> np.ndarray:
    """Unit directions of the legs in the local strain space, shape (n, dim).

    dim = 2: (d_eps_n, d_eps_t) = (cos psi_k, sin psi_k), psi_k = 2 pi k / n. dim = 3: the
    spherical Fibonacci set (nearly even on the sphere) about the isotropic axis
    e_v = (1, 1, 1) / sqrt 3: z_k e_v + sqrt(1 - z_k^2) (cos phi_k e_1 + sin phi_k e_2) with
    z_k = 1 - (2 k + 1) / n, phi_k = k pi (3 - sqrt 5), e_1 = (2, -1, -1) / sqrt 6 and
    e_2 = (0, 1, -1) / sqrt 2, so that its latitude z_k is the volumetric part of the
    direction: its rings near z = 0 are the isochoric directions every cell of an undrained
    test follows (as psi = 135 and 315 deg in 2D).
    """
    return DIMENSIONS[dim].leg_directions(settings.n_directions)


def path_length(d_eps: np.ndarray) -> np.ndarray:
    """Euclidean norm of local strain increments (n, dim), shape (n,) (``np.hypot`` of the columns)."""
    return np.hypot.reduce(d_eps, axis=1)


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
        directions: unit leg directions, shape (n, dim).
        arc: ``leg_arc`` of the settings, shape (K,).
    """
    volumetric = np.abs(directions.sum(axis=1))
    reach = settings.leg_volumetric / np.maximum(volumetric, 1e-300) * (1.0 + 1e-12)
    return np.searchsorted(arc, reach, side="right").astype(np.int64)


def turn_candidates(settings: DatabaseSettings) -> np.ndarray:
    """Indices into ``leg_arc`` of the leg's sampled states whose path length lies in ``reversal_arc``, shape (m,).

    Raises:
        ValueError: one line, where none does (with reversal legs: the turns could not lie in the arc asked for).
    """
    arc = leg_arc(settings)
    lo, hi = settings.reversal_arc
    candidates = np.flatnonzero((arc >= lo * (1.0 - 1e-12)) & (arc <= hi * (1.0 + 1e-12)))
    if not candidates.size and settings.reversal_legs:
        shown = ", ".join(f"{a:g}" for a in arc[:4]) + (", ..." if arc.size > 4 else "")
        raise ValueError(f"reversal_arc = ({lo:g}, {hi:g}) holds none of a leg's sampled path lengths ({shown}: "
                         f"sample_spacing, leg_refinement, leg_length); widen it or sample more finely")
    return candidates


def turn_draws(settings: DatabaseSettings, start_id: int, n_levels: int,
               dim: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Turns of the branches of one start cell (module docstring), each shape
    (n_levels, n_directions, reversal_legs): the leg's increments done at the turn (int64, >= 1;
    the state after them is the turn), the angle [rad] from the leg's direction to the
    branch's (counter-clockwise in the (eps_n, eps_t) plane; pi: negated) and, for dim = 3,
    a standard normal vector per branch, shape (..., 3), that picks the plane of the turn
    (``turned``); None for dim = 2. The planar draws come first, so they do not depend on dim."""
    rng = np.random.default_rng([TURN_STREAM, int(start_id)])
    candidates = turn_candidates(settings)
    shape = (n_levels, settings.n_directions, settings.reversal_legs)
    steps = candidates[rng.integers(0, candidates.size, size=shape)] + 1
    negated = rng.random(shape) < settings.reversal_negated_fraction
    turn = rng.uniform(math.radians(settings.reversal_min_angle_deg), math.pi, size=shape)
    sense = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
    plane = DIMENSIONS[dim].turn_plane(rng, shape)
    return steps.astype(np.int64), np.where(negated, math.pi, sense * turn), plane


def turned(directions: np.ndarray, angle: np.ndarray, plane: np.ndarray | None = None) -> np.ndarray:
    """Unit directions (n, dim) turned by ``angle`` [rad] (n,); pi gives exactly -direction.

    dim = 2 (``plane`` None): counter-clockwise in the (eps_n, eps_t) plane. dim = 3: towards
    the part of ``plane`` (n, 3) normal to the direction (the turn's plane; ``turn_draws``).
    """
    c, s = libm.cos(angle), libm.sin(angle)
    if plane is None:
        out = np.stack([c * directions[:, 0] - s * directions[:, 1], s * directions[:, 0] + c * directions[:, 1]],
                       axis=1)
    else:
        normal = plane - np.sum(plane * directions, axis=1, keepdims=True) * directions
        normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        out = c[:, None] * directions + s[:, None] * normal
    return np.where((angle == math.pi)[:, None], -directions, out)


def volumetric_steps(settings: DatabaseSettings, volumetric_start: np.ndarray, increments: np.ndarray) -> np.ndarray:
    """Increments of each path before its volumetric change from the leg's start exceeds
    ``leg_volumetric``, shape (n,) int64.

    Args:
        volumetric_start: sum of the local strains at the path's start minus at its leg's start [-], (n,).
        increments: local strain increments, shape (n, K, dim).
    """
    change = volumetric_start[:, None] + np.cumsum(increments.sum(axis=2), axis=1)
    within = np.abs(change) <= settings.leg_volumetric * (1.0 + 1e-12)
    return np.where(within.all(axis=1), within.shape[1], np.argmin(within, axis=1)).astype(np.int64)


def force_floor(schema: StateSchema, contact_law: ContactLaw, contact_tolerance: float) -> float:
    """Normal force [N] at or below which a cell counts as force-free: the DEM's force floor
    kn * contact_tolerance * mean grain diameter."""
    return contact_law.kn * contact_tolerance * 2.0 * float(schema.radius.mean())


def stop_masks(schema: StateSchema, arrays: Mapping[str, np.ndarray], eps: np.ndarray, stress_free_run: np.ndarray,
               settings: DatabaseSettings, contact_law: ContactLaw, contact_tolerance: float) -> dict[str, np.ndarray]:
    """Per-rule masks of the states where a path stops (``STOP_RULES``), each (n,) bool.

    Args:
        arrays: DEM state arrays (``DemCell.state_to_arrays``), first axis n.
        eps: local strains summed from the start cell [-], shape (n, dim).
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


WalkProgress = Callable[[Iterable[int], str], Iterable[int]]
"""(increment indices, walk label) -> the same indices: what wraps a walk's increment loop."""


def _unwrapped(steps: Iterable[int], label: str) -> Iterable[int]:
    """The ``WalkProgress`` that reports nothing."""
    return steps


class Explorer:
    """Walks batches of DEM cells along their paths (module docstring).

    Args:
        cell_model: a ``warp_hcell.dem.cell.DemCell`` (any object with ``step``, ``take``,
            ``state_to_arrays``).
        schema: the learning state of the cells.
        settings: generator settings.
        contact_law, contact_tolerance: the DEM's (for the force-free and overlap rules).
        n_starts: number of start cells (rows of ``stops``).
        progress: ``(increment indices, walk label) -> the same indices``, wrapping each walk's
            increment loop (a command draws a progress bar around it); None: no wrapping.
    """

    def __init__(self, cell_model, schema: StateSchema, settings: DatabaseSettings, contact_law: ContactLaw,
                 contact_tolerance: float, n_starts: int = 1, progress: WalkProgress | None = None):
        self.cell_model = cell_model
        self.progress = progress or _unwrapped
        self.schema = schema
        self.settings = settings
        self.contact_law = contact_law
        self.contact_tolerance = contact_tolerance
        self.stops = {rule: np.zeros(n_starts, np.int64) for rule in (*STOP_RULES, TURN_NOT_REACHED)}
        """How often each stop rule fired, and how many branches were not walked, per start cell."""

    def _free_run(self, arrays, previous: np.ndarray, length: np.ndarray) -> np.ndarray:
        free = stress_free(self.schema, arrays, self.contact_law, self.contact_tolerance)
        return np.where(free, previous + length, 0.0)

    def walk(self, state, increments: np.ndarray, n_steps: np.ndarray, eps_start: np.ndarray,
             free_run_start: np.ndarray, cell_start: np.ndarray, label: str, *,
             sample_start: bool) -> dict[str, np.ndarray]:
        """Advance cells along their own increments, one batch per increment, sampling each state.

        Args:
            state: the start states, n_cells cells (admissible: start cells or sampled states).
            increments: local strains [-] of increment k of cell i, shape (n_cells, K, dim)
                (a broadcast view is fine), compression positive.
            n_steps: increments allowed per cell, shape (n_cells,) int, <= K.
            eps_start: local strains of the start states from their start cell, (n_cells, dim).
            free_run_start: force-free path length of the start states, (n_cells,).
            cell_start: start cell (0..n_starts-1) of each walked cell, (n_cells,) int.
            label: the walk's name (its progress bar's label).
            sample_start: also sample the start states (step 0).

        Returns:
            The sampled states: ``cell`` (walk index) and ``step`` (increments done) int64,
            ``eps`` (n, dim), ``free_run`` (n,), and the DEM arrays prefixed ``DEM_PREFIX``.
        """
        cm = self.cell_model
        active = np.arange(increments.shape[0])
        eps, free_run = np.array(eps_start, dtype=np.float64), np.array(free_run_start, dtype=np.float64)
        parts = [self._record(cm.state_to_arrays(state), active, 0, eps, free_run)] if sample_start else []
        for k in self.progress(range(int(n_steps.max(initial=0))), label):
            going = np.flatnonzero(n_steps[active] > k)
            if going.size < active.size:
                state, active, eps, free_run = cm.take(state, going), active[going], eps[going], free_run[going]
            if not active.size:
                break
            d_eps = np.ascontiguousarray(increments[active, k])
            state, _ = cm.step(state, d_eps)
            arrays = cm.state_to_arrays(state)
            eps = eps + d_eps
            free_run = self._free_run(arrays, free_run, path_length(d_eps))
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
    """Path ids of start cell k are k * path_stride + (0: its isotropic path; 1, 2, ...: its
    legs; after the n_levels * n_directions legs: the branches, reversal_legs per leg in leg order)."""
    return 1 + len(set(settings.precompression)) * settings.n_directions * (1 + settings.reversal_legs)


def explore(cell_model, start_state, schema: StateSchema, settings: DatabaseSettings, contact_law: ContactLaw,
            contact_tolerance: float, start_ids: np.ndarray | None = None, *,
            progress: WalkProgress | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Run the exploration tree (module docstring) and return the sampled states.

    Args:
        cell_model: a ``DemCell``.
        start_state: the start cells (n_starts cells), touching and force-free.
        schema: their learning state.
        settings: generator settings.
        contact_law, contact_tolerance: the DEM's.
        start_ids: global index of each start cell, (n_starts,) int; default 0, 1, ...
        progress: wraps each walk's increment loop (``Explorer``); None: silent.

    Returns:
        (states, stops). ``states``: first axis n_states, ordered by start cell (then as walked):
        the DEM arrays (prefix ``DEM_PREFIX``), ``path_id`` and ``start_id`` int64,
        ``precompression`` [-], ``direction_deg`` [deg] (leg direction; NaN on isotropic paths;
        3D: 360 k / n_directions for direction k), ``turn_deg`` [deg] (a branch's counter-clockwise
        turn, 180 = negated; NaN elsewhere), ``eps`` (n_states, dim) [-] from the start cell.
        ``stops``: rule -> how often it fired per start cell, (n_starts,) int64."""
    n_starts = int(start_state.n_cells)
    explorer = Explorer(cell_model, schema, settings, contact_law, contact_tolerance, n_starts, progress)
    start_ids = np.arange(n_starts, dtype=np.int64) if start_ids is None else np.asarray(start_ids, np.int64)
    stride = path_stride(settings)
    levels = np.unique(np.asarray(settings.precompression, dtype=np.float64))
    iso_strain = np.union1d(levels, np.arange(0.0, levels[-1], settings.sample_spacing / math.sqrt(2.0)))
    dim = schema.dim
    iso_increments = np.repeat(np.diff(iso_strain)[None, :, None], dim, axis=2)
    iso = explorer.walk(start_state, np.broadcast_to(iso_increments, (n_starts, *iso_increments.shape[1:])),
                        np.full(n_starts, iso_increments.shape[1]), np.zeros((n_starts, dim)),
                        np.zeros(n_starts), np.arange(n_starts), "isotropic paths", sample_start=True)
    iso_eps = iso_strain[iso.pop("step")]
    cell = iso["cell"]
    iso.update(path_id=start_ids[cell] * stride, start_id=start_ids[cell], precompression=iso_eps,
               direction_deg=np.full(iso_eps.size, np.nan))

    reached = np.isin(levels, iso_eps)
    if not reached.all():
        raise UnreachableLevel(f"precompression {levels[~reached][0]:g}: no start cell reaches it on its isotropic path "
                               f"(the paths stop by the exploration's stop rules, e.g. an overlap above max_overlap "
                               f"{settings.max_overlap:g} (r_i + r_j); the largest isotropic strain reached: "
                               f"{iso_eps.max(initial=0.0):g}); give levels up to that")
    origin = np.flatnonzero(np.isin(iso_eps, levels))
    directions = leg_directions(settings, dim)
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
    # leg number within its start cell, in creation order (whatever the other start cells)
    leg_start = iso["start_id"][leg_origin]
    by_start = np.argsort(leg_start, kind="stable")
    rank = np.empty(leg_start.size, np.int64)
    rank[by_start] = np.arange(leg_start.size) - np.searchsorted(leg_start[by_start], leg_start[by_start])
    leg_level = np.searchsorted(levels, iso_eps[leg_origin])
    branches = turn_branches(explorer, cell_model, legs, directions, leg_dir, leg_level, leg_start, leg_origin,
                             iso, iso_eps, arc, levels.size)
    step, cell = legs.pop("step"), legs.pop("cell")
    start = leg_origin[cell]
    legs.update(path_id=leg_start[cell] * stride + 1 + rank[cell], start_id=leg_start[cell],
                precompression=iso_eps[start], direction_deg=360.0 * leg_dir[cell] / n_dir,
                turn_deg=np.full(cell.size, np.nan))
    if branches is not None:
        leg, branch, angle = branches.pop("leg"), branches.pop("branch"), branches.pop("angle")
        branches.update(path_id=leg_start[leg] * stride + 1 + levels.size * n_dir
                        + rank[leg] * settings.reversal_legs + branch, start_id=leg_start[leg],
                        precompression=iso_eps[leg_origin[leg]], direction_deg=360.0 * leg_dir[leg] / n_dir,
                        turn_deg=np.degrees(angle))
    iso.pop("cell")
    iso["turn_deg"] = np.full(iso_eps.size, np.nan)
    parts = [iso, legs] if branches is None else [iso, legs, branches]
    states = {name: np.concatenate([part[name] for part in parts]) for name in iso}
    states.pop("free_run")
    order = np.argsort(states["start_id"], kind="stable")
    return {name: value[order] for name, value in states.items()}, explorer.stops


def turn_branches(explorer: Explorer, cell_model, legs: Mapping[str, np.ndarray], directions: np.ndarray,
                  leg_dir: np.ndarray, leg_level: np.ndarray, leg_start: np.ndarray, leg_origin: np.ndarray,
                  iso: Mapping[str, np.ndarray], iso_eps: np.ndarray, arc: np.ndarray,
                  n_levels: int) -> dict[str, np.ndarray] | None:
    """Walk the turning branches of the walked legs (module docstring); None without branches.

    Args:
        explorer: the exploration's walker (its stop counts get ``TURN_NOT_REACHED``).
        legs: ``Explorer.walk`` output of the legs (``cell`` = leg index, ``step``).
        directions: unit leg directions, (n_directions, dim); leg_dir, leg_level, leg_start,
            leg_origin: per leg, its direction index, precompression level index, start id
            and isotropic state (index into ``iso``), each (n_legs,) int.
        iso: the isotropic paths' states (``cell``: local start cell); iso_eps: their
            isotropic strain [-]; arc: ``leg_arc``; n_levels: precompression levels.

    Returns:
        The branch states as walked (``Explorer.walk``: DEM arrays, ``eps``, ``free_run``),
        with ``leg`` (parent leg index), ``branch`` (0..reversal_legs-1) int64 and ``angle``
        [rad] per state.
    """
    settings = explorer.settings
    n_rev = settings.reversal_legs
    if not n_rev or not leg_dir.size:
        return None
    dim = directions.shape[1]
    steps = np.empty((leg_dir.size, n_rev), np.int64)
    angle = np.empty((leg_dir.size, n_rev))
    plane = None
    for start_id in np.unique(leg_start):
        mine = leg_start == start_id
        turn_step, turn_angle, turn_plane = turn_draws(settings, int(start_id), n_levels, dim)
        steps[mine] = turn_step[leg_level[mine], leg_dir[mine]]
        angle[mine] = turn_angle[leg_level[mine], leg_dir[mine]]
        if turn_plane is not None:
            plane = np.empty((leg_dir.size, n_rev, dim)) if plane is None else plane
            plane[mine] = turn_plane[leg_level[mine], leg_dir[mine]]
    leg = np.repeat(np.arange(leg_dir.size), n_rev)
    branch = np.tile(np.arange(n_rev), leg_dir.size)
    steps, angle = steps.ravel(), angle.ravel()
    plane = None if plane is None else plane.reshape(-1, dim)
    key = legs["cell"] * (arc.size + 1) + legs["step"]
    order = np.argsort(key, kind="stable")
    want = leg * (arc.size + 1) + steps
    at = np.minimum(np.searchsorted(key[order], want), key.size - 1)
    reached = key[order][at] == want
    np.add.at(explorer.stops[TURN_NOT_REACHED], iso["cell"][leg_origin[leg[~reached]]], 1)
    leg, branch, angle, row = leg[reached], branch[reached], angle[reached], order[at[reached]]
    plane = None if plane is None else plane[reached]
    if not leg.size:
        return None
    dem = {name[len(DEM_PREFIX):]: value[row] for name, value in legs.items() if name.startswith(DEM_PREFIX)}
    new_direction = turned(directions[leg_dir[leg]], angle, plane)
    increments = np.diff(arc, prepend=0.0)[None, :, None] * new_direction[:, None, :]
    eps = legs["eps"][row]
    volumetric = eps.sum(axis=1) - dim * iso_eps[leg_origin[leg]]
    n_steps = volumetric_steps(settings, volumetric, increments)
    if not n_steps.any():
        return None
    walked = explorer.walk(cell_model.state_from_arrays(dem), increments, n_steps, eps, legs["free_run"][row],
                           iso["cell"][leg_origin[leg]], "turning branches", sample_start=False)
    walked.pop("step")
    index = walked.pop("cell")
    walked.update(leg=leg[index], branch=branch[index], angle=angle[index])
    return walked
