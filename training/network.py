"""``CellNet``: the meso-ANN of one H-cell increment (spec section 11), architecture only.

Contract. ``CellNet.predict`` maps a batch of database-convention inputs (n, 8)
``d_eps_n, d_eps_t, alpha_deg, N1, N2, T1, l1, l2`` (probe [-], compression positive, and
PRE-increment state [deg, N, N, N, m, m]) to the POST-increment state (n, 4)
``alpha_deg, N1, N2, T1`` [deg, N, N, N]. Everything is float64 (an increment of ~1e-4 deg
on alpha ~ 55 deg would lose 3 % to float32 rounding).

How the 8 inputs become features (the normalisation of the spec, then z-scores):

- the probe is split into its magnitude m = |d_eps| [-] and direction
  u = d_eps / m (u = 0 where m = 0);
- the state is made dimensionless: alpha [rad], N1, N2, T1 / (kn D), l1, l2 / D;
- derived features expose what switches the cell's incremental response and is a sharp
  function of the inputs (hard for a small tanh network to resolve near zero force or at
  the Coulomb cap): the contact flags ``closed1 = [N1 > 0]``, ``closed2 = [N2 > 0]``, the
  friction ratio ``T1 / N1`` (0 where N1 = 0) and the sliding flag ``slip = sign(T1)`` where
  |T1| >= mu N1 (1 - ``SLIP_TOLERANCE``) on a closed contact, else 0;
- the 12 features ``(u_n, u_t, alpha, N1, N2, T1, l1, l2, closed1, closed2, T1/N1, slip)``
  are z-scored with training statistics. The magnitude m is deliberately not a feature:
  with log10(m) as a 13th feature the network fitted finite-probe effects with a wild
  m-dependence and the constant-volume run drifted 8 % of p0 from the analytical curve
  at 1e-4 increments (0.25 % at 1e-5); without it, 0.4 % at both.

The multilayer perceptron (tanh hidden layers, linear output) returns z-scored
dimensionless *rates* r = increment / m of ``(alpha [rad], N1, N2, T1 [kn D])``; the
increment is m * r. The cell response is rate independent, so the increment is (to first
order) homogeneous of degree 1 in the probe: this structure makes a zero probe give an
exactly zero increment and lets one network serve probes spanning decades of magnitude
with the same relative accuracy. The scales (kn, D) and z-score statistics are registered
buffers, so they travel in the ``state_dict``.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

N_INPUTS = 8
"""Physical inputs: d_eps_n, d_eps_t [-], alpha_deg [deg], N1, N2, T1 [N], l1, l2 [m]."""
N_OUTPUTS = 4
"""Physical outputs: alpha_deg [deg], N1, N2, T1 [N] after the increment."""
N_FEATURES = 12
"""Network inputs derived from the physical inputs (see the module docstring)."""
SLIP_TOLERANCE = 1e-4
"""Relative distance to the Coulomb cap mu N1 [-] within which a contact counts as sliding.
The DEM's quasi-static tolerance leaves sliding contacts up to ~1e-5 below the cap; a
contact 1e-4 below it starts sliding after ~1e-6 of strain, less than the smallest probe."""
DEFAULT_HIDDEN: tuple[int, ...] = (8, 8, 8)
"""Hidden layer widths of the spec (3 x 8 tanh)."""
ACTIVATION = "tanh"
"""Hidden activation (the output layer is linear)."""


def probe_split(d_eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Magnitude (n, 1) [-] and unit direction (n, 2) of probes d_eps (n, 2); u = 0 where m = 0."""
    magnitude = torch.linalg.vector_norm(d_eps, dim=1, keepdim=True)
    direction = torch.where(magnitude > 0, d_eps / torch.where(magnitude > 0, magnitude, 1.0), 0.0)
    return magnitude, direction


def dimensionless_state(state: torch.Tensor, kn: torch.Tensor | float, diameter: torch.Tensor | float) -> torch.Tensor:
    """State (n, 6) ``alpha_deg, N1, N2, T1, l1, l2`` [deg, N, N, N, m, m] -> radians, kn D, D units."""
    force = kn * diameter
    return torch.cat(
        [torch.deg2rad(state[:, :1]), state[:, 1:4] / force, state[:, 4:6] / diameter],
        dim=1,
    )


def features(
    inputs: torch.Tensor, kn: torch.Tensor | float, diameter: torch.Tensor | float, mu: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Un-z-scored features (n, 12) and probe magnitudes (n, 1) of physical inputs (n, 8).

    ``kn`` [N/m], ``diameter`` [m] and the friction coefficient ``mu`` [-] are those of the
    training data.
    """
    magnitude, direction = probe_split(inputs[:, :2])
    state = dimensionless_state(inputs[:, 2:], kn, diameter)
    N1, N2, T1 = state[:, 1:2], state[:, 2:3], state[:, 3:4]
    closed1 = N1 > 0
    ratio = torch.where(closed1, T1 / torch.where(closed1, N1, 1.0), 0.0)
    slip = torch.where(closed1 & (torch.abs(T1) >= mu * N1 * (1.0 - SLIP_TOLERANCE)), torch.sign(T1), 0.0)
    derived = [closed1.to(state.dtype), (N2 > 0).to(state.dtype), ratio, slip]
    return torch.cat([direction, state, *derived], dim=1), magnitude


class CellNet(nn.Module):
    """Tanh multilayer perceptron with its normalisation buffers (float64).

    Args:
        hidden: widths of the hidden layers (default 3 x 8).
        kn: normal contact stiffness of the training data [N/m] (force scale kn D).
        diameter: grain diameter D = 2 r of the training data [m] (length scale).
        mu: friction coefficient tan(phi_g) of the training data [-] (sliding flag).

    Buffers (set with ``set_normalisation`` before training, restored by
    ``load_state_dict``): ``feature_mean``, ``feature_std`` (12,) and ``rate_mean``,
    ``rate_std`` (4,) in dimensionless units; ``kn`` [N/m], ``diameter`` [m], ``mu`` [-].
    """

    def __init__(self, hidden: Sequence[int] = DEFAULT_HIDDEN, *, kn: float = 1.0, diameter: float = 1.0,
                 mu: float = 1.0) -> None:
        super().__init__()
        self.hidden = tuple(int(h) for h in hidden)
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden = {list(self.hidden)} must be a non-empty list of widths >= 1")
        widths = (N_FEATURES, *self.hidden)
        layers: list[nn.Module] = []
        for n_in, n_out in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(n_in, n_out, dtype=torch.float64), nn.Tanh()]
        layers.append(nn.Linear(widths[-1], N_OUTPUTS, dtype=torch.float64))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("kn", torch.tensor(float(kn), dtype=torch.float64))
        self.register_buffer("diameter", torch.tensor(float(diameter), dtype=torch.float64))
        self.register_buffer("mu", torch.tensor(float(mu), dtype=torch.float64))
        self.register_buffer("feature_mean", torch.zeros(N_FEATURES, dtype=torch.float64))
        self.register_buffer("feature_std", torch.ones(N_FEATURES, dtype=torch.float64))
        self.register_buffer("rate_mean", torch.zeros(N_OUTPUTS, dtype=torch.float64))
        self.register_buffer("rate_std", torch.ones(N_OUTPUTS, dtype=torch.float64))

    def set_normalisation(self, feature_mean, feature_std, rate_mean, rate_std) -> None:
        """Copy z-score statistics (dimensionless features (12,), rates (4,)) into the buffers."""
        for name, value in (("feature_mean", feature_mean), ("feature_std", feature_std),
                            ("rate_mean", rate_mean), ("rate_std", rate_std)):
            getattr(self, name).copy_(torch.as_tensor(value, dtype=torch.float64))

    def forward(self, z_features: torch.Tensor) -> torch.Tensor:
        """z-scored features (n, 12) -> z-scored dimensionless rates (n, 4)."""
        return self.mlp(z_features)

    def normalise(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Physical inputs (n, 8) -> z-scored features (n, 12) and probe magnitudes m (n, 1)."""
        raw, magnitude = features(inputs, self.kn, self.diameter, self.mu)
        return (raw - self.feature_mean) / self.feature_std, magnitude

    def increment(self, inputs: torch.Tensor) -> torch.Tensor:
        """Physical inputs (n, 8) -> increments (n, 4) of ``alpha [rad], N1, N2, T1 [N]``."""
        z, magnitude = self.normalise(inputs)
        rate = self(z) * self.rate_std + self.rate_mean
        scale = torch.stack([torch.ones_like(self.kn), *(3 * [self.kn * self.diameter])])
        return magnitude * rate * scale

    @torch.no_grad()
    def predict(self, inputs: torch.Tensor) -> torch.Tensor:
        """Physical inputs (n, 8) -> POST-increment ``alpha_deg, N1, N2, T1`` (n, 4) [deg, N].

        No clipping: a negative force is returned as predicted (the caller decides, see
        ``homogenization.backends.ann``).
        """
        inputs = torch.as_tensor(inputs, dtype=torch.float64)
        increment = self.increment(inputs)
        alpha_deg = inputs[:, 2:3] + increment[:, :1] * (180.0 / math.pi)
        return torch.cat([alpha_deg, inputs[:, 3:6] + increment[:, 1:]], dim=1)
