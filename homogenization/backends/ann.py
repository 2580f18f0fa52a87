"""Meso-ANN H-cell backend (spec section 11): a trained ``CellNet`` replaces the equilibrium solve.

``AnnCell`` implements ``warp_hcell.cell_model.CellModel``. Per macro increment, ONE
batched network call over all cells maps the probe (d_eps_n, d_eps_t) and the state at the
start of the increment (alpha, N1, N2, T1, l1, l2) to the end values of (alpha, N1, N2,
T1). What is not learned:

- l1, l2 follow the imposed strain (spec section 3): l1 <- l1 (1 - d_eps_n),
  l2 <- l2 (1 - d_eps_t);
- the geometry d1 = l2 / (2 sin a), d2 = l1 - 2 d1 cos a and the Love-Weber moment with
  its pathological contacts come from ``homogenization.backends.hcell`` (spec section 7).

Non-physical network outputs are mapped onto the contact law, never silently: a negative
normal force becomes 0 (no tension, N = max(N, 0), as the contact law itself does), and
|T1| > mu N1 is capped at mu N1 with the sign of the prediction (Coulomb, so an open
contact carries no tangential force).

Stress-free mechanisms are not learned (the database cleaning removes them: their alpha
is not fixed by equilibrium) and follow spec sections 5-6 instead. When a contact opens
so that grain 2 cannot be in equilibrium along n with the other one closed (N1 = 0, or
N2 = 0 with alpha < 90 deg - phi_g), every force drops to 0 and the cell becomes a
mechanism: y2 = d2/2 is kept (chosen in the range where both contacts are open or
touching) and alpha, d1 follow l1, l2 by kinematics. The network is still called for
these cells (one call per increment for the whole batch) and its prediction is used again
from the increment in which the kinematics closes a contact. Where l1, l2 leave no y2
with both contacts open, the cell stays closed and N2 is set by the equilibrium of grain
2 along n, N2 = max(N1 cos a + T1 sin a, 0) (spec section 5).

Each ``step`` reports in ``CellResponse.diagnostics`` how many cells were affected:
``n_tension_clipped`` (N1 or N2 < 0 predicted), ``n_coulomb_capped``, ``n_mechanism``
(cells in the mechanism state after the increment), ``n_equilibrium_n2`` (N2 from
equilibrium) and ``n_alpha_outside`` (alpha outside [30, 90] deg, left as predicted).

Sign convention: compression and contraction positive; T1 > 0 resists opening (alpha
growing). Local frame: index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from homogenization.backends import hcell
from warp_hcell.cell_model import ArrayStateMixin, CellResponse
from training.checkpoint import CheckpointError, check_compatible, load_checkpoint
from warp_hcell.parameters import ALPHA_MAX_DEG, ALPHA_MIN_DEG, ContactLaw, check_positive

DEFAULT_MODEL = "ann_default.pt"
"""File name of the model shipped in ``homogenization/data`` (with its ``.json``)."""


def default_model_path() -> Path:
    """Path of the shipped default model state_dict (its metadata sits next to it).

    Found next to the package's modules (package data ``homogenization/data``), which works
    for regular and editable installs alike.
    """
    return Path(__file__).resolve().parents[1] / "data" / DEFAULT_MODEL


class AnnState(NamedTuple):
    """Batch of ANN H-cells; every field has shape (n_cells,)."""

    alpha: np.ndarray
    """Opening angle [rad]."""
    N1: np.ndarray
    """Normal force of the type-1 contacts [N], compression positive."""
    N2: np.ndarray
    """Normal force of the type-2 contacts [N], compression positive."""
    T1: np.ndarray
    """Tangential force of the type-1 contacts [N], > 0 resists opening."""
    l1: np.ndarray
    """Axial length, centre 1 to centre 4 [m]."""
    l2: np.ndarray
    """Distance between the lateral columns [m]."""
    y2_free: np.ndarray
    """n-coordinate of grain 2 [m] kept while the cell is a stress-free mechanism; NaN otherwise."""


def mechanism_y2(l1: np.ndarray, l2: np.ndarray, d2: np.ndarray, diameter: float) -> np.ndarray:
    """y2 [m] of a cell entering the mechanism state: d2 / 2 clipped to where d1, d2 >= D.

    Args:
        l1, l2: cell lengths [m], shape (n,).
        d2: type-2 branch length of the prediction [m], shape (n,).
        diameter: grain diameter D [m].

    Returns:
        y2 [m], shape (n,); NaN where no y2 opens both contacts (d1 >= D needs
        y2 <= l1/2 - sqrt(D^2 - l2^2/4), d2 >= D needs y2 >= D/2).
    """
    y2_max = 0.5 * l1 - np.sqrt(np.maximum(diameter**2 - 0.25 * l2**2, 0.0))
    y2_min = np.full_like(l1, 0.5 * diameter)
    return np.where(y2_min <= y2_max, np.clip(0.5 * d2, y2_min, y2_max), np.nan)


class AnnCell(ArrayStateMixin):
    """H-cell whose increment is predicted by a trained ``training.network.CellNet``.

    Args:
        contact_law: contact stiffnesses and friction; must match the model's training data.
        radius: grain radius r [m]; must match the model's training data.
        model: path of a model state_dict (``.pt``, metadata in the ``.json`` next to it);
            None loads the default model shipped in ``homogenization/data``.
        device: torch device of the network ("cpu", "cuda", ...).

    Raises:
        training.checkpoint.CheckpointError: (a ValueError, one line) missing, corrupt or
            mismatched model file, or a model trained for another contact law or radius.
    """

    name = "ann"
    state_type = AnnState

    def __init__(self, contact_law: ContactLaw, radius: float, *, model: str | Path | None = None, device: str = "cpu") -> None:
        self.contact_law = contact_law
        self.radius = check_positive("radius", radius)
        self.diameter = 2.0 * self.radius
        self.kn = contact_law.kn
        self.mu = contact_law.mu
        self.alpha_lock = math.radians(90.0 - contact_law.phi_g_deg)
        """Opening angle [rad] above which a cell with N2 = 0 can be friction-locked (spec section 5)."""
        path = default_model_path() if model is None else Path(model)
        if model is None and not path.is_file():
            raise CheckpointError(f"{path}: the default ANN model is not installed; pass model=PATH (--model)")
        self.net, self.metadata = load_checkpoint(path)
        check_compatible(self.metadata, kn=contact_law.kn, kt_over_kn=contact_law.kt_over_kn,
                         phi_g_deg=contact_law.phi_g_deg, radius=self.radius, source=str(path))
        self.model_path = path
        self.device = torch.device(device)
        self.net.to(self.device)

    def init_state(self, alpha0_deg: float | np.ndarray, n_cells: int) -> AnnState:
        """Touching, force-free cells: d1 = d2 = D at opening angle alpha0.

        Args:
            alpha0_deg: initial opening angle [deg], scalar or shape (n_cells,), each in
                [30, 90); ValueError otherwise.
            n_cells: number of cells.
        """
        alpha, l1, l2 = hcell.touching_cells(alpha0_deg, n_cells, self.diameter)
        zero = np.zeros_like(alpha)
        return AnnState(alpha, zero, zero.copy(), zero.copy(), l1, l2, np.full_like(alpha, np.nan))

    def step(self, state: AnnState, d_eps_local: np.ndarray) -> tuple[AnnState, CellResponse]:
        """Advance every cell by its local strain increment with one network call; pure.

        Args:
            state: cells at the start of the increment.
            d_eps_local: (d_eps_n, d_eps_t) [-], shape (n_cells, 2), compression positive.

        Returns:
            The state at the end of the increment and its response (diagnostics: counts of
            cells whose prediction was mapped onto the contact law, see the module docstring).
        """
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        inputs = np.column_stack([d_eps, np.degrees(state.alpha), state.N1, state.N2, state.T1, state.l1, state.l2])
        with torch.inference_mode():
            out = self.net.predict(torch.from_numpy(inputs).to(self.device)).cpu().numpy()
        alpha = np.radians(out[:, 0])
        N1 = np.maximum(out[:, 1], 0.0)
        N2 = np.maximum(out[:, 2], 0.0)
        cap = self.mu * N1
        T1 = np.clip(out[:, 3], -cap, cap)
        l1 = state.l1 * (1.0 - d_eps[:, 0])
        l2 = state.l2 * (1.0 - d_eps[:, 1])
        alpha, N1, N2, T1, y2_free, balanced = self._mechanisms(state.y2_free, alpha, N1, N2, T1, l1, l2)
        new = AnnState(alpha, N1, N2, T1, l1, l2, y2_free)
        moment, area = hcell.love_weber_moment(alpha, N1, N2, T1, l1, l2, kn=self.kn, diameter=self.diameter)
        alpha_deg = np.degrees(alpha)
        diagnostics = {
            "n_tension_clipped": float(np.count_nonzero((out[:, 1] < 0.0) | (out[:, 2] < 0.0))),
            "n_coulomb_capped": float(np.count_nonzero(np.abs(out[:, 3]) > cap)),
            "n_mechanism": float(np.count_nonzero(np.isfinite(y2_free))),
            "n_equilibrium_n2": float(np.count_nonzero(balanced)),
            "n_alpha_outside": float(np.count_nonzero((alpha_deg < ALPHA_MIN_DEG) | (alpha_deg > ALPHA_MAX_DEG))),
        }
        return new, CellResponse(moment, area, diagnostics)

    def _mechanisms(self, y2_old, alpha, N1, N2, T1, l1, l2):
        """Apply the mechanism rules of the module docstring to a clamped prediction.

        Args:
            y2_old: ``y2_free`` at the start of the increment [m], shape (n_cells,).
            alpha [rad], N1, N2, T1 [N]: prediction after the contact-law mapping.
            l1, l2: lengths at the end of the increment [m].

        Returns:
            (alpha, N1, N2, T1, y2_free, balanced): the end state and the mask of cells
            whose N2 was set by grain-2 equilibrium; all shape (n_cells,).
        """
        D = self.diameter
        was_free = np.isfinite(y2_old)
        # a mechanism keeps y2 while the kinematics leaves both contacts open
        d1_k, d2_k, alpha_k = hcell.branches_from_y2(l1, l2, np.where(was_free, y2_old, 0.5 * l1))
        stays_free = was_free & (d1_k >= D) & (d2_k >= D)
        # a cell that loses grain-2 equilibrium with a closed contact becomes a mechanism ...
        unbalanced = ~was_free & ((N1 == 0.0) | ((N2 == 0.0) & (alpha < self.alpha_lock)))
        _, d2 = hcell.branches_from_alpha(l1, l2, alpha)
        y2_new = np.where(unbalanced, mechanism_y2(l1, l2, d2, D), np.nan)
        enters = np.isfinite(y2_new)
        # ... unless l1, l2 keep a contact closed: then grain-2 equilibrium gives N2 (spec section 5)
        balanced = unbalanced & ~enters
        N2 = np.where(balanced, np.maximum(N1 * np.cos(alpha) + T1 * np.sin(alpha), 0.0), N2)
        _, _, alpha_e = hcell.branches_from_y2(l1, l2, np.where(enters, y2_new, 0.5 * l1))
        alpha = np.where(stays_free, alpha_k, np.where(enters, alpha_e, alpha))
        free = stays_free | enters
        N1, N2, T1 = (np.where(free, 0.0, f) for f in (N1, N2, T1))
        return alpha, N1, N2, T1, np.where(stays_free, y2_old, y2_new), balanced

    def response(self, state: AnnState) -> CellResponse:
        """Meso-stress of ``state`` without advancing it."""
        moment, area = hcell.love_weber_moment(state.alpha, state.N1, state.N2, state.T1, state.l1, state.l2,
                                               kn=self.kn, diameter=self.diameter)
        return CellResponse(moment, area)

    def observables(self, state: AnnState) -> dict[str, np.ndarray]:
        """Named per-cell quantities, each shape (n_cells,).

        ``l1, l2, d1, d2`` [m] (d1, d2 from l1, l2, alpha), ``alpha_deg`` [deg],
        ``N1, N2, T1`` [N] (compression positive, T1 > 0 resists opening), ``S_nn, S_tt``
        [N m], ``area`` [m^2], ``closed1, closed2`` (bool: the contact carries a normal
        force) and grain centres ``x_n{i}, x_t{i}`` [m], labels i = 1..6.
        """
        response = self.response(state)
        d1, d2 = hcell.branches_from_alpha(state.l1, state.l2, state.alpha)
        return hcell.observables(state.l1, state.l2, d1, d2, state.alpha, state.N1, state.N2, state.T1,
                                 response.moment, response.area)

