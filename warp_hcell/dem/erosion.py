"""Erosion: remove grains from a mesostructure and from a DEM state, mid-test.

``remove_grains(meso, grains)`` returns the mesostructure without ``grains`` (0-based) and
the index maps of the grains and pairs it keeps; ``erode_arrays(arrays, removal)`` maps a
batch state, as given by ``DemCell.state_to_arrays`` (per-grain arrays on axis 1 of shape
(n_cells, n_grains, ...), per-pair arrays (n_cells, n_pairs, ...), the topology replaced by
the reduced one, per-cell arrays kept),
onto the reduced mesostructure; ``erode_state(cell, state, grains)`` does both and returns
the ``DemCell`` of the reduced mesostructure with its state. Nothing here knows a shape:
any grain that is not part of the outer polygon can be removed.

What removal does to the mechanics: the contact forces and tangential spring histories of
the removed grains' pairs disappear; every other array (positions, velocities, the history
of the remaining pairs, cell size, per-cell reference geometry) is kept as it is. The state
is then out of balance; the next DEM step relaxes it (quasi-statically, at the cell strain
it is given, possibly zero).

``erodible_grains(meso)`` is the default choice: the grains with no driven DOF (free along
n and t: fines loose in the pore).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import numpy as np

from warp_hcell.dem.cell import DemCell, DemCellState
from warp_hcell.mesostructures.mesostructure import Mesostructure, MesostructureError, TOPOLOGY_ARRAYS, topology_arrays

PER_GRAIN = ("position", "velocity", "radius", "reference_position")
"""State/model arrays with one entry per grain on axis 1."""
PER_PAIR = ("shear_force", "contact_force", "contact")
"""State arrays with one entry per candidate pair on axis 1."""


@dataclass(frozen=True)
class GrainRemoval:
    """A mesostructure with grains removed, and where its grains and pairs came from.

    Attributes:
        meso: the reduced mesostructure.
        removed: removed grains, 0-based indices in the original, shape (n_removed,).
        grain_index: original index of each kept grain, shape (n_grains_kept,).
        pair_index: original index of each kept pair, shape (n_pairs_kept,).
    """

    meso: Mesostructure
    removed: np.ndarray
    grain_index: np.ndarray
    pair_index: np.ndarray


def erodible_grains(meso: Mesostructure) -> np.ndarray:
    """0-based indices of the grains with no driven DOF (free along n and t), shape (n,)."""
    return np.flatnonzero(~meso.driven.any(axis=1))


def remove_grains(meso: Mesostructure, grains: Sequence[int]) -> GrainRemoval:
    """``meso`` without ``grains`` (0-based indices).

    Pairs with a removed grain are dropped; the others are renumbered (their labels kept);
    the outer polygon and the declared observables are renumbered (those of a removed grain
    dropped); the parameters are kept.

    Raises:
        MesostructureError: no grain given, an index out of range, or a grain of the outer
            polygon (one line).
    """
    removed = np.unique(np.asarray(grains, dtype=np.int64).reshape(-1))
    if removed.size == 0:
        raise MesostructureError(f"mesostructure {meso.name!r}: no grain to remove")
    if removed.min() < 0 or removed.max() >= meso.n_grains:
        raise MesostructureError(f"mesostructure {meso.name!r}: grain {int(removed.max()) + 1} to remove does not "
                                 f"exist (grains 1..{meso.n_grains})")
    outer = sorted(set(removed.tolist()) & set(meso.outer.tolist()))
    if outer:
        raise MesostructureError(f"mesostructure {meso.name!r}: grain {outer[0] + 1} is on the outer polygon "
                                 f"and cannot be removed")
    keep = np.setdiff1d(np.arange(meso.n_grains), removed)
    new_index = np.full(meso.n_grains, -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    pair_keep = np.flatnonzero(np.all(new_index[meso.pairs] >= 0, axis=1))
    labels = "+".join(str(g + 1) for g in removed.tolist())
    observables = tuple(replace(o, grains=(int(new_index[o.grains[0]]), int(new_index[o.grains[1]])))
                        for o in meso.observables if np.all(new_index[list(o.grains)] >= 0))
    reduced = Mesostructure(
        name=f"{meso.name} without grain {labels}", radius=meso.radius[keep], position=meso.position[keep],
        driven=meso.driven[keep], pairs=new_index[meso.pairs[pair_keep]], outer=new_index[meso.outer],
        cell_size=meso.cell_size, pair_label=meso.pair_label[pair_keep], observables=observables,
        parameters=meso.parameters, contact_tolerance=meso.contact_tolerance)
    return GrainRemoval(reduced, removed, keep, pair_keep)


def erode_arrays(arrays: Mapping[str, Any], removal: GrainRemoval) -> dict[str, np.ndarray]:
    """Map batch arrays (``DemCell.state_to_arrays``) onto the reduced mesostructure.

    Args:
        arrays: name -> array with first axis n_cells; names in ``PER_GRAIN`` are indexed by
            grain on axis 1, names in ``PER_PAIR`` by pair on axis 1, names in
            ``warp_hcell.mesostructures.mesostructure.TOPOLOGY_ARRAYS`` are replaced by the reduced mesostructure's,
            the rest are per cell.
        removal: from ``remove_grains``.

    Returns:
        New arrays (copies), same names.
    """
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        if name in PER_GRAIN:
            out[name] = value[:, removal.grain_index].copy()
        elif name in PER_PAIR:
            out[name] = value[:, removal.pair_index].copy()
        elif name in TOPOLOGY_ARRAYS:
            out[name] = topology_arrays(removal.meso, value.shape[0])[name]
        else:
            out[name] = value.copy()
    return out


def erode_state(cell: DemCell, state: DemCellState,
                grains: Sequence[int] | None = None) -> tuple[DemCell, DemCellState, GrainRemoval]:
    """Remove ``grains`` (0-based; default ``erodible_grains``) from every cell of a DEM batch.

    Args:
        cell: the ``warp_hcell.dem.cell.DemCell`` that produced ``state``.
        state: its ``DemCellState``.
        grains: grains to remove; None = the grains with no driven DOF.

    Returns:
        (reduced_cell, reduced_state, removal): a ``DemCell`` of the reduced mesostructure
        (same contact law, settings, device, threads), the mapped state, and the
        ``GrainRemoval``.
    """
    meso = state.model.meso
    grains = erodible_grains(meso) if grains is None else grains
    removal = remove_grains(meso, grains)
    reduced = DemCell(cell.contact_law, cell.radius, settings=cell.settings, device=cell.device,
                      threads=cell.threads)
    return reduced, reduced.state_from_arrays(erode_arrays(cell.state_to_arrays(state), removal)), removal
