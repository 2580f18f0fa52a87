"""The DEM started from rest in every increment: the reference of the certificate's own reproducibility.

A DEM state carries a memory of the increment that produced it (``warp_hcell.dem.state.DemState.velocity``),
from which the next step sets its driving rate and predicts its free grains (``warp_hcell.dem.kernels``,
"memory", "adaptive rate and prediction"). ``FromRest`` forgets it before every step
(``warp_hcell.dem.cell.DemCell.at_rest``, which also drives the increment at
``DemSettings.rest_strain_per_substep``): each increment starts from rest, as the database probes every
state (``warp_hcell.database.probing``), so it is the map the network is trained on. Where the response
drops in a sawtooth (a fine grain leaving its wedge), when a drop happens depends on such details; the
two DEMs differ there by what the certificate cannot resolve (``certificate.certify``, ``dem_spread``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from warp_hcell.core.contract import CellResponse
from warp_hcell.dem.cell import DemCell, DemCellState


class FromRest:
    """The DEM cell model ``model`` with every increment started from rest: ``step`` steps
    ``model.at_rest(state)``; ``name`` is ``model``'s with " from rest" (the backend a run records),
    every other attribute ``model``'s."""

    def __init__(self, model: DemCell) -> None:
        self.model = model
        self.name = f"{model.name} from rest"

    def __getattr__(self, name: str) -> Any:
        return getattr(self.model, name)

    def step(self, state: DemCellState, d_eps_local: np.ndarray, *,
             with_tangent: bool = False) -> tuple[DemCellState, CellResponse]:
        """``DemCell.step`` of ``state`` at rest: (d_eps_n, d_eps_t[, d_eps_t2]) [-], shape (n_cells, dim),
        compression positive; pure."""
        return self.model.step(self.model.at_rest(state), d_eps_local, with_tangent=with_tangent)
