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

from warp_hcell.core.parameters import CellDefaults, ContactLaw

BACKENDS: dict[str, str] = {
    "analytical": "homogenization.backends.analytical:AnalyticalCell",
    "dem": "homogenization.backends.dem:DemCell",
    "ann": "homogenization.backends.ann:AnnCell",
}
"""Backend name -> "module:Class" of its implementation."""


def backend_class(name: str) -> type:
    """Return the class implementing backend ``name``; ValueError (one line) if unknown."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
    module_name, class_name = BACKENDS[name].split(":")
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
    **options: Any,
):
    """Construct backend ``name`` with the given physical parameters and options."""
    return backend_class(name)(contact_law or ContactLaw(), radius, **options)


def mesostructure_refusal(name: str, meso: Any) -> str | None:
    """Why backend ``name`` does not model the mesostructure ``meso`` (one line), or None if it may.

    Asks the class's static ``check_mesostructure`` where it has one; a backend without it
    models any mesostructure (an ANN model still refuses, in ``init_state``, a mesostructure
    it was not trained on).
    """
    check = getattr(backend_class(name), "check_mesostructure", None)
    if check is None:
        return None
    try:
        check(meso)
    except ValueError as exc:
        return str(exc)
    return None
