"""What the meso-DEM does differently for planar cells (disks) and spatial cells (spheres), chosen
once by the cell's dimension: ``DIMENSIONS[meso.dim]``.

The kernels of both dimensions share their stepping and pair loops (``warp_hcell.dem.stepping``,
``warp_hcell.dem.pairs``); what differs on the host is the kernel of a topology and the sliding test
of the tangent. A grain's measure (its mass) and the shape of a spring are the dimension's data
(``warp_hcell.core.dimension``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import warp as wp

from warp_hcell.core.parameters import Law
from warp_hcell.dem.kernels import step_kernel
from warp_hcell.dem.kernels3d import step_kernel_3d
from warp_hcell.dem.tangent import sliding_contacts, sliding_contacts_3d
from warp_hcell.mesostructures.mesostructure import Mesostructure


def _planar_kernel(meso: Mesostructure, law: str) -> wp.Kernel:
    """The planar cell-step kernel of ``meso``'s topology and outer polygon (the linear law, ``law``)."""
    return step_kernel(*meso.topology_key(), tuple(int(g) for g in meso.outer))


def _spatial_kernel(meso: Mesostructure, law: str) -> wp.Kernel:
    """The spatial cell-step kernel of ``meso``'s topology and outer faces with contact law ``law``."""
    return step_kernel_3d(*meso.topology_key(), tuple(map(tuple, meso.outer.tolist())), law)


@dataclass(frozen=True)
class DemDimension:
    """The pieces of the meso-DEM of one spatial dimension."""

    kernel: Callable[[Mesostructure, str], wp.Kernel]
    """(mesostructure, contact-law name) -> the compiled cell-step kernel of its topology."""
    sliding_contacts: Callable[..., np.ndarray]
    """``warp_hcell.dem.tangent.sliding_contacts`` or ``sliding_contacts_3d``."""
    steps: Callable[[Law], bool]
    """contact law -> True where the kernel steps it: in the plane only the laws defined for disks
    (``Law.planar``), in space every law."""


DIMENSIONS = {
    2: DemDimension(_planar_kernel, sliding_contacts, lambda law: law.planar),
    3: DemDimension(_spatial_kernel, sliding_contacts_3d, lambda law: True),
}
"""The meso-DEM's pieces by the cell's dimension."""
