"""Test doubles of the cell-model protocol (not backends): closed-form elastic cells.

``ElasticCell`` is a nonlinear elastic cell: S_nn = k V (e_n + c e_t + b e_n^2),
S_tt = k V (e_t + c e_n + b e_t^2), S_nt = 0, constant area V, where (e_n, e_t) are the
accumulated local strains (compression positive). It is path independent, so the driver's
results can be checked against closed forms, and nonlinear, so Newton must iterate. Its
``step(..., with_tangent=True)`` returns the closed-form tangent d(S_nn, S_tt)/d(e_n, e_t).
"""

from __future__ import annotations

import numpy as np


class ElasticCell:
    """Nonlinear elastic stand-in for a cell backend (state = accumulated local strains)."""

    name = "elastic"

    def __init__(self, contact_law=None, radius: float = 0.5, *, stiffness: float = 1e8,
                 coupling: float = 0.3, quadratic: float = 5.0) -> None:
        self.k, self.c, self.b = stiffness, coupling, quadratic
        self.area = (2.0 * radius) ** 2

    def init_state(self, mesostructure, n_cells: int) -> np.ndarray:
        return np.zeros((n_cells, 2))

    def response(self, state: np.ndarray, *, with_tangent: bool = False):
        from warp_hcell.core.contract import CellResponse

        en, et = state[:, 0], state[:, 1]
        kv = self.k * self.area
        moment = np.zeros((state.shape[0], 2, 2))
        moment[:, 0, 0] = kv * (en + self.c * et + self.b * en**2)
        moment[:, 1, 1] = kv * (et + self.c * en + self.b * et**2)
        tangent = None
        if with_tangent:
            tangent = np.empty((state.shape[0], 2, 2))
            tangent[:, 0, 0] = kv * (1.0 + 2.0 * self.b * en)
            tangent[:, 0, 1] = kv * self.c
            tangent[:, 1, 0] = kv * self.c
            tangent[:, 1, 1] = kv * (1.0 + 2.0 * self.b * et)
        return CellResponse(moment, np.full(state.shape[0], self.area), {"calls": 1.0}, tangent)

    def step(self, state: np.ndarray, d_eps_local: np.ndarray, *, with_tangent: bool = False):
        new = state + d_eps_local
        return new, self.response(new, with_tangent=with_tangent)

    def observables(self, state: np.ndarray) -> dict[str, np.ndarray]:
        return {"eps_n": state[:, 0].copy(), "eps_t": state[:, 1].copy()}

    def take(self, state: np.ndarray, index: np.ndarray) -> np.ndarray:
        return state[np.asarray(index)]

    def state_to_arrays(self, state: np.ndarray) -> dict[str, np.ndarray]:
        return {"eps": state.copy()}

    def state_from_arrays(self, arrays) -> np.ndarray:
        return np.array(arrays["eps"], dtype=np.float64)
