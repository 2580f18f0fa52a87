"""The contact laws of the DEM kernels (Warp, float64), one module per law, found by the law's name
(``warp_hcell.core.laws.law_module``: "hertz-mindlin" is ``hertz_mindlin.py``).

A law's module gives the pair loops (``warp_hcell.dem.pairs``) and the spatial kernel
(``warp_hcell.dem.kernels3d``) three ``@wp.func`` and the DEM model (``warp_hcell.dem.model``,
``warp_hcell.dem.integrator``) two host functions:

- ``pair_scale(r_i, r_j, r_sum)``: a per-pair factor [m^0.5 or 1] of the kernel's two constants,
  computed once per increment from the radii [m];
- ``pair_constant(k, scale)``: a pair's constant from the kernel's constant k and the pair's factor;
- ``normal_force(overlap, kn)`` [N] with a pair's constant, never tension;
- ``spatial_contact(u, rel, overlap, spring, kn, kt, mu)``: one spatial pair within reach, with its
  pair constants (``warp_hcell.dem.pairs``: (f_n [N], new spring vector [N], regime 1 sticking, 2
  sliding));
- ``kernel_constants(law)`` -> (kn, kt, mu) as the kernel takes them;
- ``reference_stiffness(law, radius)`` [N/m]: the normal stiffness that sets a cell's time step and
  force floor, a float or (n_cells,) from ``radius`` (n_cells, n_grains) [m].

The planar kernel (``warp_hcell.dem.kernels``) steps the linear law only (the one law of disks,
``planar`` in its declaration).
"""

from __future__ import annotations

from types import ModuleType

from warp_hcell.core.laws import law_module


def warp_law(name: str) -> ModuleType:
    """The Warp module of contact law ``name`` (module docstring); ValueError (one line) for a name no
    law is registered under."""
    return law_module(__name__, name)
