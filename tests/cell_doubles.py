"""Test doubles of the cell-model protocol (not backends): closed-form elastic cells.

``ElasticCell`` is a nonlinear elastic cell of the mesostructure's dimension d (2 or 3): along each
local axis a, S_aa = k V (e_a + c sum_{b != a} e_b + b e_a^2), off-diagonal moments 0, constant
measure V = (2 r)^d, where e are the accumulated local strains (compression positive). It is path
independent, so the driver's results can be checked against closed forms, and nonlinear, so
Newton must iterate. Its ``step(..., with_tangent=True)`` returns the closed-form tangent
d(S_aa)/d(e_b).
"""

from __future__ import annotations

from functools import reduce

import numpy as np

from warp_hcell.core.dimension import dimension


class ElasticCell:
    """Nonlinear elastic stand-in for a cell backend (state = accumulated local strains (n_cells, d))."""

    name = "elastic"

    def __init__(self, contact_law=None, radius: float = 0.5, *, stiffness: float = 1e8,
                 coupling: float = 0.3, quadratic: float = 5.0) -> None:
        self.k, self.c, self.b = stiffness, coupling, quadratic
        self.size = 2.0 * radius
        self.area = self.size**2
        """The measure V of a planar cell [m^2]."""

    def init_state(self, mesostructure, n_cells: int) -> np.ndarray:
        return np.zeros((n_cells, getattr(mesostructure, "dim", 2)))

    def response(self, state: np.ndarray, *, with_tangent: bool = False):
        from warp_hcell.core.contract import CellResponse

        n, d = state.shape
        measure = self.size**d
        kv = self.k * measure
        moment = np.zeros((n, d, d))
        for a in range(d):
            others = reduce(np.add, [state[:, b] for b in range(d) if b != a])
            moment[:, a, a] = kv * (state[:, a] + self.c * others + self.b * state[:, a] ** 2)
        tangent = None
        if with_tangent:
            tangent = np.full((n, d, d), kv * self.c)
            for a in range(d):
                tangent[:, a, a] = kv * (1.0 + 2.0 * self.b * state[:, a])
        return CellResponse(moment, np.full(n, measure), {"calls": 1.0}, tangent)

    def step(self, state: np.ndarray, d_eps_local: np.ndarray, *, with_tangent: bool = False):
        new = state + d_eps_local
        return new, self.response(new, with_tangent=with_tangent)

    def observables(self, state: np.ndarray) -> dict[str, np.ndarray]:
        return {f"eps_{axis}": state[:, a].copy() for a, axis in enumerate(dimension(state.shape[1]).frame)}

    def take(self, state: np.ndarray, index: np.ndarray) -> np.ndarray:
        return state[np.asarray(index)]

    def state_to_arrays(self, state: np.ndarray) -> dict[str, np.ndarray]:
        return {"eps": state.copy()}

    def state_from_arrays(self, arrays) -> np.ndarray:
        return np.array(arrays["eps"], dtype=np.float64)
