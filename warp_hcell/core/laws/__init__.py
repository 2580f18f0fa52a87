"""The contact laws of the package, one module per law and runtime, found by the law's name.

A law is declared once (its dataclass in ``warp_hcell.core.parameters``, registered in
``CONTACT_LAWS`` by its ``name``); each runtime that carries it holds it in one module named after
the law ("hertz-mindlin": ``hertz_mindlin.py``) inside the runtime's ``laws`` package:

- numpy (this package; the closed form and the DEM tangent through ``warp_hcell.core.contact.PairLaw``):
  ``pair_constants(law, radius_i, radius_j)`` -> (kn, kt), the law's two constants for a batch of
  pairs, and, elementwise over overlaps [m] with those constants, ``normal_force(overlap, kn)`` [N],
  ``normal_stiffness(overlap, kn)`` and ``shear_stiffness(overlap, kt)`` [N/m],
  ``move_stiffness(start_overlap, overlap, kt)`` [N/m] (the stiffness by which a move grows the
  tangential spring) and ``move_stiffness_slope(start_overlap, overlap, kt)`` [N/m^2];
- Warp (``warp_hcell.dem.laws``; the DEM kernels).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from warp_hcell.core.parameters import CONTACT_LAWS


def law_module(package: str, name: str) -> ModuleType:
    """The module of contact law ``name`` (a key of ``CONTACT_LAWS``) in the runtime package ``package``
    (e.g. ``warp_hcell.core.laws``); ValueError (one line) for a name no law is registered under."""
    if name not in CONTACT_LAWS:
        raise ValueError(f"unknown contact law {name!r}; choose from {', '.join(CONTACT_LAWS)}")
    return importlib.import_module(f"{package}.{name.replace('-', '_')}")


def numpy_law(name: str) -> ModuleType:
    """The numpy module of contact law ``name`` (module docstring)."""
    return law_module(__name__, name)
