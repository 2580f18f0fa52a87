"""Immutable DEM model of a batch of cells: per-cell reference geometry, masses, constants.

``DemModel.build`` replicates one mesostructure (or stacks one per cell, same topology);
``DemModel.from_reference`` takes per-cell reference arrays. A model is never modified:
``take`` and ``from_reference`` return new models. ``model.state()`` gives the touching,
force-free initial state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import warp as wp

from warp_hcell.mesostructures.mesostructure import Mesostructure, MesostructureError, cell_measure, per_cell
from warp_hcell.core.parameters import ContactLaw, DemSettings, Law
from warp_hcell.core.dimension import dimension
from warp_hcell.dem.dimensions import DIMENSIONS
from warp_hcell.dem.laws import warp_law
from warp_hcell.dem.state import DemState
from warp_hcell.dem.stepping import cell_vector


@dataclass(frozen=True, eq=False)
class DemModel:
    """Device arrays and constants of a batch of cells sharing one topology.

    Attributes:
        meso: topology template (pairs, driven mask, outer polygon, pair labels).
        device: Warp device name.
        radius: grain radii [m], shape (n_cells, n_grains).
        inv_mass: 1 / (density pi r^2) [1/kg] per grain, shape (n_cells, n_grains).
        reference_position: reference centres [m], shape (n_cells, n_grains) vec2d.
        reference_cell_size: (l1_ref, l2_ref) [m], shape (n_cells,) vec2d.
        dt: time step dt_factor sqrt(m_min / kn) [s] of each cell (its lightest grain), (n_cells,);
            kn is the law's ``reference_stiffness`` (``warp_hcell.dem.laws``; the Hertz-Mindlin law: its
            tangent stiffness at an overlap of ``HERTZ_DT_OVERLAP`` (r_i + r_j) of the cell's smallest pair).
        force_floor: kn * contact_tolerance * mean grain diameter [N], shape (n_cells,): the
            force below which the resolution of contact detection is reached; the unbalanced
            force ratio is taken relative to max(largest normal force, force_floor).
        contact_law: normal/tangential stiffness and friction.
        settings: numerical settings (damping, strain per substep, tolerances).
    """

    meso: Mesostructure
    device: str
    radius: wp.array
    inv_mass: wp.array
    reference_position: wp.array
    reference_cell_size: wp.array
    dt: wp.array
    force_floor: wp.array
    contact_law: Law
    settings: DemSettings

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return int(self.dt.shape[0])

    @classmethod
    def from_reference(cls, meso: Mesostructure, radius: np.ndarray, reference_position: np.ndarray,
                       reference_cell_size: np.ndarray, *, contact_law: ContactLaw = ContactLaw(),
                       settings: DemSettings = DemSettings(), device: str = "cpu") -> "DemModel":
        """Model from per-cell reference arrays.

        Args:
            meso: topology template.
            radius: (n_cells, n_grains) [m].
            reference_position: (n_cells, n_grains, dim) [m].
            reference_cell_size: (n_cells, dim) [m].

        A grain's mass is density pi r^2 (a disk per unit thickness) in 2D, density 4/3 pi r^3 in 3D.
        """
        if not DIMENSIONS[meso.dim].steps(contact_law):
            raise ValueError(f"the {contact_law.name} contact law is defined for spheres (3D cells); "
                             f"mesostructure {meso.name!r} is planar: use the linear law")
        radius = np.ascontiguousarray(radius, dtype=np.float64)
        mass = settings.density * dimension(meso.dim).grain_measure(radius)
        kn = warp_law(contact_law.name).reference_stiffness(contact_law, radius)
        dt = settings.dt_factor * np.sqrt(mass.min(axis=1) / kn)
        floor = kn * settings.contact_tolerance * 2.0 * radius.mean(axis=1)

        def put(a, dtype):
            return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=dtype, device=device)

        vector = cell_vector(meso.dim)
        return cls(meso=meso, device=str(device), radius=put(radius, wp.float64), inv_mass=put(1.0 / mass, wp.float64),
                   reference_position=put(reference_position, vector),
                   reference_cell_size=put(reference_cell_size, vector), dt=put(dt, wp.float64),
                   force_floor=put(floor, wp.float64), contact_law=contact_law, settings=settings)

    @classmethod
    def build(cls, meso: Mesostructure | Sequence[Mesostructure], n_cells: int, *,
              contact_law: ContactLaw = ContactLaw(), settings: DemSettings = DemSettings(),
              device: str = "cpu") -> "DemModel":
        """Replicate one mesostructure ``n_cells`` times, or stack one per cell.

        Args:
            meso: a template, or a sequence of n_cells mesostructures with the same topology
                (pairs, driven mask, outer polygon, pair labels); radii and positions may differ.
            n_cells: number of cells.
        """
        distinct, index = per_cell(meso, n_cells)
        first = distinct[0]
        key = (first.topology_key(), first.outer.tolist(), first.pair_label.tolist())
        for m in distinct:
            if (m.topology_key(), m.outer.tolist(), m.pair_label.tolist()) != key:
                raise MesostructureError(f"mesostructure {m.name!r} has another topology than {first.name!r}")
        return cls.from_reference(
            first, np.stack([m.radius for m in distinct])[index], np.stack([m.position for m in distinct])[index],
            np.stack([m.cell_size for m in distinct])[index], contact_law=contact_law, settings=settings,
            device=device)

    def take(self, index: np.ndarray) -> "DemModel":
        """Model of cells ``index`` (int array, repetition allowed)."""
        index = np.asarray(index, dtype=np.int64)
        return DemModel.from_reference(
            self.meso, self.radius.numpy()[index], self.reference_position.numpy()[index],
            self.reference_cell_size.numpy()[index], contact_law=self.contact_law, settings=self.settings,
            device=self.device)

    def state(self) -> DemState:
        """Touching, force-free initial state: grains at their reference positions, at rest."""
        n_cells, n_pairs, dim = self.n_cells, self.meso.n_pairs, self.meso.dim
        position = self.reference_position.numpy()
        return DemState.from_numpy({
            "position": position, "velocity": np.zeros_like(position),
            "shear_force": np.zeros((n_cells, n_pairs, *dimension(dim).spring_shape)),
            "contact_force": np.zeros((n_cells, n_pairs, dim)),
            "contact": initial_contacts(position, self.radius.numpy(), self.meso.pairs,
                                        self.settings.contact_tolerance),
            "cell_size": self.reference_cell_size.numpy(), "moment": np.zeros((n_cells, dim, dim)),
            "area": cell_measure(position, self.meso.outer), "substeps": np.zeros(n_cells, np.int32),
            "converged": np.ones(n_cells, np.int32)}, self.device)


def initial_contacts(position: np.ndarray, radius: np.ndarray, pairs: np.ndarray, tolerance: float) -> np.ndarray:
    """Contact flags (int32, (n_cells, n_pairs)): gap <= tolerance * (r_i + r_j)."""
    i, j = pairs[:, 0], pairs[:, 1]
    dist = np.linalg.norm(position[:, j] - position[:, i], axis=-1)
    rsum = radius[:, i] + radius[:, j]
    return (dist - rsum <= tolerance * rsum).astype(np.int32)
