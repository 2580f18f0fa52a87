"""Registry of cell-model backends: ``--backend`` choices map to implementing classes.

Backends are imported lazily, so using the analytical backend never imports Warp or torch.
Every class takes ``(contact_law, radius, **options)`` and implements
``warp_hcell.core.contract.CellModel``: its cells are created from a mesostructure
(``init_state(mesostructure, n_cells)``). A class that models only some mesostructures also
has a static ``check_mesostructure(meso)`` that raises ValueError (one line) for the others,
so that callers can leave such cases out before building the backend (``mesostructure_refusal``).
"""

from __future__ import annotations

import importlib
from typing import Any

from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import CellDefaults, ContactLaw

BACKENDS: dict[str, dict[int, str]] = {
    "analytical": {2: "homogenization.backends.analytical:AnalyticalCell",
                   3: "homogenization.backends.analytical:Analytical3DCell"},
    "dem": {2: "homogenization.backends.dem:DemCell", 3: "homogenization.backends.dem:DemCell"},
    "ann": {2: "homogenization.ann.cell:AnnCell", 3: "homogenization.ann.cell:AnnCell3D"},
}
"""Backend name -> spatial dimension of the cells (2 or 3) -> "module:Class" of its implementation (a plain
"module:Class" registers a backend of planar cells)."""


def backend_class(name: str, dim: int = 2) -> type:
    """Return the class implementing backend ``name`` for cells of dimension ``dim``; ValueError (one line)
    if unknown or not available in that dimension."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
    by_dim = BACKENDS[name] if isinstance(BACKENDS[name], dict) else {2: BACKENDS[name]}
    if dim not in by_dim:
        raise ValueError(f"backend {name!r} does not model {dim}D cells")
    module_name, class_name = by_dim[dim].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise ValueError(f"backend {name!r} is not available in this version") from exc
        raise
    return getattr(module, class_name)


def make_cell_model(
    name: str,
    *,
    contact_law: ContactLaw | None = None,
    radius: float = CellDefaults.radius,
    dim: int = 2,
    **options: Any,
):
    """Construct backend ``name`` for cells of dimension ``dim`` (the mesostructure's ``dim``) with the given
    physical parameters and options; ValueError (one line) for a contact law the cells' dimension does not
    define (the Hertz-Mindlin law of spheres in planar cells)."""
    law = contact_law or ContactLaw()
    if dimension(dim).planar and not law.planar:
        raise ValueError(f"the {law.name} contact law is defined for spheres (3D cells, hmodel triaxial); planar "
                         f"cells use the linear law")
    return backend_class(name, dim)(law, radius, **options)


def mesostructure_refusal(name: str, meso: Any) -> str | None:
    """Why backend ``name`` does not model the mesostructure ``meso`` (one line), or None if it may.

    Asks the class's static ``check_mesostructure`` where it has one; a backend without it
    models any mesostructure (an ANN model still refuses, in ``init_state``, a mesostructure
    it was not trained on).
    """
    try:
        cls = backend_class(name, getattr(meso, "dim", 2))
    except ValueError as exc:
        return str(exc)
    check = getattr(cls, "check_mesostructure", None)
    if check is None:
        return None
    try:
        check(meso)
    except ValueError as exc:
        return str(exc)
    return None
