"""Time-varying DEM state of a batch of cells (Warp arrays, float64); created by ``DemModel.state``.

Everything that evolves lives here; every parameter lives in ``DemModel``. Frame: local
(n, t), component 0 = n. Forces are the DEM's tension-positive contact forces (see
``warp_hcell.dem.kernels``); the last step's per-cell substep count and convergence flag are kept
with the state they produced.
"""

from __future__ import annotations

import math
import sys
import threading
from dataclasses import dataclass, fields
from typing import Mapping

import numpy as np
import warp as wp

_ALIGN = 64
"""Byte alignment of each field inside the allocation of ``DemState.empty``."""
_DTYPES = {
    2: {"position": wp.vec2d, "velocity": wp.vec2d, "shear_force": wp.float64, "contact_force": wp.vec2d,
        "contact": wp.int32, "cell_size": wp.vec2d, "moment": wp.mat22d, "area": wp.float64, "substeps": wp.int32,
        "converged": wp.int32},
    3: {"position": wp.vec3d, "velocity": wp.vec3d, "shear_force": wp.vec3d, "contact_force": wp.vec3d,
        "contact": wp.int32, "cell_size": wp.vec3d, "moment": wp.mat33d, "area": wp.float64, "substeps": wp.int32,
        "converged": wp.int32},
}
"""Warp dtype of every field, for planar (2) and spatial (3) cells."""


@dataclass(frozen=True, eq=False)
class DemState:
    """Arrays of one batch state; ``vecd`` is vec2d (dim 2, frame (n, t)) or vec3d (dim 3, (n, t1, t2)).

    Attributes:
        position: grain centres [m], (n_cells, n_grains) vecd.
        velocity: each grain's mean velocity over the producing step's driving substeps [m/s],
            (n_cells, n_grains) vecd.
        shear_force: tangential spring force on grain i [N]: 2D a scalar along w = (-u_t, u_n),
            (n_cells, n_pairs); 3D a tangent-plane vec3d.
        contact_force: force on grain i of pair (i, j) by grain j [N], (n_cells, n_pairs) vecd.
        contact: 1 where the pair is in contact, (n_cells, n_pairs) int32.
        cell_size: (l1, l2[, l3]) [m], (n_cells,) vecd.
        moment: Love-Weber sum sum_p f_p (x) (x_j - x_i) [N m], tension positive, (n_cells,)
            mat22d/mat33d, rows = force, columns = branch component.
        area: V_cell [m^2 or m^3] through the outer grains, (n_cells,).
        substeps, converged: substeps spent by the producing step, 1 where it reached
            equilibrium, (n_cells,) int32."""

    position: wp.array
    velocity: wp.array
    shear_force: wp.array
    contact_force: wp.array
    contact: wp.array
    cell_size: wp.array
    moment: wp.array
    area: wp.array
    substeps: wp.array
    converged: wp.array

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return int(self.cell_size.shape[0])

    @property
    def dim(self) -> int:
        """Spatial dimension of the cells (2 or 3)."""
        return 3 if self.position.dtype is wp.vec3d else 2

    @classmethod
    def empty(cls, n_cells: int, n_grains: int, n_pairs: int, device: str, dim: int = 2) -> "DemState":
        """Uninitialised state arrays (to be filled by a step or by ``from_numpy``).

        Every step allocates one state: the fields are views into one allocation (38 instead
        of 46 us of CPU per state of 360 cells, measured); each view keeps the block alive
        through an attribute, so the block is freed with the last view (or numpy view of one).
        """
        shapes = {"position": (n_cells, n_grains), "velocity": (n_cells, n_grains),
                  "shear_force": (n_cells, n_pairs), "contact_force": (n_cells, n_pairs),
                  "contact": (n_cells, n_pairs), "cell_size": (n_cells,), "moment": (n_cells,), "area": (n_cells,),
                  "substeps": (n_cells,), "converged": (n_cells,)}
        dtypes = _DTYPES[dim]
        offsets, total = {}, 0
        for name, shape in shapes.items():
            offsets[name] = total
            size = math.prod(shape) * wp.types.type_size_in_bytes(dtypes[name])
            total += -(-size // _ALIGN) * _ALIGN
        block = wp.empty(max(total, 1), dtype=wp.uint8, device=device)
        fields_ = {}
        for name, shape in shapes.items():
            view = wp.array(ptr=block.ptr + offsets[name], dtype=dtypes[name], shape=shape, device=device)
            view.memory_block = block
            fields_[name] = view
        return cls(**fields_)

    @classmethod
    def from_numpy(cls, arrays: Mapping[str, np.ndarray], device: str) -> "DemState":
        """State from numpy arrays named like the fields (vector fields with a trailing axis of the
        dimension, ``moment`` with trailing axes (dim, dim)); the dimension is that of ``position``."""
        dtypes = _DTYPES[int(np.shape(arrays["position"])[-1])]

        def put(name):
            host = np.ascontiguousarray(arrays[name], dtype=np.int32 if dtypes[name] is wp.int32 else np.float64)
            return wp.array(host, dtype=dtypes[name], device=device)

        return cls(**{f.name: put(f.name) for f in fields(cls)})

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Numpy views (CPU) or copies (GPU) of every field, named like the fields."""
        return {f.name: getattr(self, f.name).numpy() for f in fields(self)}


class StatePool:
    """Output states of a batch's steps, reused once nothing outside the pool refers to them.

    States are values (a step writes a new one and never modifies its input); allocating one costs
    more CPU than the kernel spends on a small batch. ``acquire`` hands out a state nobody can
    observe any more: its reference counts (the state, each field array) are back at what they
    were when only the pool held it. A reference held elsewhere (a caller's state, a
    ``DemCellState``, a numpy view of a field) keeps it out of reuse; then, or when every pooled
    state is in use, a new state is allocated. A step overwrites every field of its output. Each
    thread has its own pool.

    Args:
        n_cells, n_grains, n_pairs: batch dimensions; device: Warp device; dim: 2 or 3.
        capacity: most states kept per thread."""

    def __init__(self, n_cells: int, n_grains: int, n_pairs: int, device: str, capacity: int = 8, dim: int = 2):
        self._shape = (int(n_cells), int(n_grains), int(n_pairs), device, int(dim))
        self._capacity = int(capacity)
        self._local = threading.local()

    def acquire(self) -> DemState:
        """A state whose fields the caller may overwrite (uninitialised or from a dropped step)."""
        entries = self._entries()
        for entry in entries:
            if entry.unreferenced():
                return entry.state
        if len(entries) < self._capacity:
            entries.append(_PoolEntry(self._shape))
            return entries[-1].state
        return DemState.empty(*self._shape)

    def _entries(self) -> list["_PoolEntry"]:
        entries = getattr(self._local, "entries", None)
        if entries is None:
            entries = self._local.entries = []
        return entries


class _PoolEntry:
    """A pooled state and the reference counts of its objects while only the pool holds it."""

    def __init__(self, shape: tuple):
        self.state = DemState.empty(*shape)
        self.fields = tuple(getattr(self.state, f.name) for f in fields(DemState))
        self.baseline = self._counts()

    def _counts(self) -> tuple[int, ...]:
        return (sys.getrefcount(self.state), *(sys.getrefcount(a) for a in self.fields))

    def unreferenced(self) -> bool:
        """True when nothing outside the pool refers to the state or to one of its fields."""
        return self._counts() == self.baseline
