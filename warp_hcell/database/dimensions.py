"""What the database does differently for planar and spatial cells, chosen once by the cell's
dimension: ``DIMENSIONS[dim]``.

The legs' directions, the draws of a turn's plane and of a probe's direction, and the contact
forces of a learning state (``warp_hcell.database.learning_state``). Sign convention:
compression and contraction positive; forces are the DEM's (the learning state's docstring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from warp_hcell.core import libm
from warp_hcell.core.contact import CAP_SLACK, coulomb_cap


def _circle(n: int) -> np.ndarray:
    """(d_eps_n, d_eps_t) = (cos psi_k, sin psi_k), psi_k = 2 pi k / n, shape (n, 2)."""
    psi = 2.0 * np.pi * np.arange(n) / n
    return np.stack([libm.cos(psi), libm.sin(psi)], axis=1)


def _fibonacci_sphere(n: int) -> np.ndarray:
    """The spherical Fibonacci set about e_v = (1, 1, 1) / sqrt 3, shape (n, 3)
    (``warp_hcell.database.exploration.leg_directions``)."""
    k = np.arange(n)
    z = 1.0 - (2.0 * k + 1.0) / n
    ring, phi = np.sqrt(1.0 - z * z), k * np.pi * (3.0 - math.sqrt(5.0))
    e_1, e_2, e_v = np.array([[2.0, -1.0, -1.0], [0.0, 1.0, -1.0], [1.0, 1.0, 1.0]]) / np.sqrt([[6.0], [2.0], [3.0]])
    # term by term, not a matrix product: BLAS picks its kernel (FMA or not) by CPU
    return (ring * libm.cos(phi))[:, None] * e_1 + (ring * libm.sin(phi))[:, None] * e_2 + z[:, None] * e_v


def _no_plane(rng: np.random.Generator, shape: tuple[int, ...]) -> None:
    """A planar turn stays in the (eps_n, eps_t) plane: no draw."""
    return None


def _normal_plane(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """A standard normal vector per turn, shape (*shape, 3), that picks its plane."""
    return libm.standard_normal(rng, (*shape, 3))


def _planar_probes(gen: np.random.Generator, n: int, magnitude: Callable[[], np.ndarray]) -> np.ndarray:
    """Probes (n, 2): an angle uniform in [0, 2 pi) drawn before the magnitudes (n,) ``magnitude()`` draws."""
    angle = gen.uniform(0.0, 2.0 * np.pi, n)
    return magnitude()[:, None] * np.stack([libm.cos(angle), libm.sin(angle)], axis=1)


def _spatial_probes(gen: np.random.Generator, n: int, magnitude: Callable[[], np.ndarray]) -> np.ndarray:
    """Probes (n, 3): a normalised standard normal vector drawn after the magnitudes (n,) ``magnitude()`` draws."""
    size = magnitude()
    direction = libm.standard_normal(gen, (n, 3))
    return size[:, None] * direction / np.linalg.norm(direction, axis=1, keepdims=True)


def _planar_forces(shear_force: np.ndarray, normal: np.ndarray, u: np.ndarray, touching: np.ndarray,
                   mu: float) -> tuple[np.ndarray, np.ndarray]:
    """(capped spring forces (n, n_pairs), forces on grain i (n, n_pairs, 2)) of planar pairs."""
    shear = np.where(touching, coulomb_cap(np.asarray(shear_force, dtype=np.float64), normal, mu), 0.0)
    force = np.stack([-normal * u[..., 0] - shear * u[..., 1], -normal * u[..., 1] + shear * u[..., 0]], axis=-1)
    return shear, force


def _spatial_forces(shear_force: np.ndarray, normal: np.ndarray, u: np.ndarray, touching: np.ndarray,
                    mu: float) -> tuple[np.ndarray, np.ndarray]:
    """(capped spring vectors (n, n_pairs, 3), forces on grain i (n, n_pairs, 3)) of spatial pairs:
    the spring is scaled down to mu f_n where longer by more than ``CAP_SLACK`` (the 3D DEM's cap,
    ``warp_hcell.dem.contact``, made idempotent)."""
    trial = np.asarray(shear_force, dtype=np.float64)
    size = np.sqrt(np.sum(trial * trial, axis=-1))
    cap = mu * normal
    scale = np.where(size > cap * (1.0 + CAP_SLACK), cap / np.where(size > 0.0, size, 1.0), 1.0)
    shear = np.where(touching[..., None], trial * scale[..., None], 0.0)
    return shear, shear - normal[..., None] * u


@dataclass(frozen=True)
class DatabaseDimension:
    """The database's pieces of one spatial dimension.

    Attributes:
        leg_directions: n -> the legs' unit directions (n, dim) in the local strain space.
        turn_plane: (generator, shape) -> what picks each turn's plane, ``(*shape, 3)``, or None
            (a planar turn; ``warp_hcell.database.exploration.turned``).
        probes: (generator, n, magnitude) -> probes (n, dim) [-]: the direction draws around the
            magnitudes (n,) that ``magnitude()`` draws from the same generator.
        pair_forces: (springs [N], f_n (n, n_pairs) [N], unit normals u (n, n_pairs, dim),
            contact flags, mu) -> (the springs after the Coulomb cap, zero out of contact [N],
            the forces on grain i (n, n_pairs, dim) [N]).
    """

    leg_directions: Callable[[int], np.ndarray]
    turn_plane: Callable[[np.random.Generator, tuple[int, ...]], np.ndarray | None]
    probes: Callable[[np.random.Generator, int, Callable[[], np.ndarray]], np.ndarray]
    pair_forces: Callable[..., tuple[np.ndarray, np.ndarray]]


DIMENSIONS = {
    2: DatabaseDimension(_circle, _no_plane, _planar_probes, _planar_forces),
    3: DatabaseDimension(_fibonacci_sphere, _normal_plane, _spatial_probes, _spatial_forces),
}
"""The database's pieces by the cell's dimension."""
