"""Closed-form geometry and meso-stress of the symmetric H-cell (spec sections 2, 3, 7).

Shared by the analytical and the ANN backends. Every function is vectorised over cells:
arguments are arrays of shape (n_cells,) (or scalars that broadcast) and nothing is
looped over in Python.

Local cell frame: index 0 = n (cell axis), index 1 = t (lateral direction). Grain labels
1..6 as in spec section 2 (array index = label - 1)::

          1              1 = (n:  l1/2, t: 0)
       2     6           2 = (n:  y2,   t: -l2/2)    6 = (n:  y2, t: +l2/2)
       3     5           3 = (n: -y2,   t: -l2/2)    5 = (n: -y2, t: +l2/2)
          4              4 = (n: -l1/2, t: 0)

with y2 = d2/2, l1 = d2 + 2 d1 cos(alpha) and l2 = 2 d1 sin(alpha). Angles in radians.
Sign convention: compression positive (contact forces N1, N2 > 0 push grains apart, the
Love-Weber moment of a compressed cell is positive); T1 > 0 resists opening (alpha
growing).
"""

from __future__ import annotations

import numpy as np

from warp_hcell.core.parameters import ALPHA_MAX_DEG, ALPHA_MIN_DEG, check_alpha0_deg

N_GRAINS = 6
"""Number of grains of the H-cell [-]."""


def lengths(d1: np.ndarray, d2: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell lengths from the branch lengths (spec section 2).

    Args:
        d1: type-1 branch length [m], shape (n_cells,).
        d2: type-2 branch length [m], shape (n_cells,).
        alpha: opening angle between the axis n and the branch 1->2 [rad], shape (n_cells,).

    Returns:
        (l1, l2) [m]: axial length centre 1 to centre 4, and distance between the lateral
        columns, each shape (n_cells,).
    """
    return d2 + 2.0 * d1 * np.cos(alpha), 2.0 * d1 * np.sin(alpha)


def branches_from_alpha(
    l1: np.ndarray, l2: np.ndarray, alpha: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Branch lengths from the cell lengths and the opening angle (spec section 11).

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        alpha: opening angle [rad], shape (n_cells,), in (0, pi/2].

    Returns:
        (d1, d2) [m]: d1 = l2 / (2 sin alpha), d2 = l1 - 2 d1 cos alpha; shape (n_cells,).
    """
    d1 = 0.5 * l2 / np.sin(alpha)
    return d1, l1 - 2.0 * d1 * np.cos(alpha)


def cell_area(l1: np.ndarray, l2: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Area of the hexagon through the six centres (spec section 2).

    V_cell = l2 (d2 + d1 cos alpha) = l2 (l1 + d2) / 2, since 2 d1 cos alpha = l1 - d2.

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        d2: type-2 branch length [m], shape (n_cells,).

    Returns:
        V_cell [m^2], shape (n_cells,).
    """
    return 0.5 * l2 * (l1 + d2)


def grain_positions(l1: np.ndarray, l2: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Centres of the six grains in the local frame, cell centre at the origin.

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        y2: n-coordinate of grain 2, d2/2 [m], shape (n_cells,).

    Returns:
        Positions [m], shape (n_cells, 6, 2): [:, label - 1, 0] = x_n, [:, label - 1, 1] = x_t.
    """
    l1, l2, y2 = np.broadcast_arrays(
        np.asarray(l1, dtype=np.float64), np.asarray(l2, dtype=np.float64), np.asarray(y2, dtype=np.float64)
    )
    hn, ht = 0.5 * l1, 0.5 * l2
    zero = np.zeros_like(hn)
    x_n = np.stack([hn, y2, -y2, -hn, -y2, y2], axis=-1)
    x_t = np.stack([zero, -ht, -ht, zero, ht, ht], axis=-1)
    return np.stack([x_n, x_t], axis=-1)


def love_weber_moment(
    alpha: np.ndarray,
    N1: np.ndarray,
    N2: np.ndarray,
    T1: np.ndarray,
    l1: np.ndarray,
    l2: np.ndarray,
    *,
    kn: float,
    diameter: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Love-Weber moment S = sum_c f_c (x) l_c of the H-cell and its area (spec section 7).

    Sums the four type-1 contacts (normal N1, tangential T1), the two type-2 contacts
    (normal N2) and the pathological contacts that the six-contact cell ignores in its
    equilibrium: grains 1-4 when l1 < D (force kn (D - l1) along n) and grains 2-6, 3-5
    when l2 < D (force kn (D - l2) each, along t). In the local frame:

        S_nn = 4 d1 cos a (N1 cos a + T1 sin a) + 2 N2 d2 + kn <D - l1> l1
        S_tt = 4 d1 sin a (N1 sin a - T1 cos a) + 2 kn <D - l2> l2,   S_nt = 0,

    with d1 = l2 / (2 sin a) and d2 = l1 - 2 d1 cos a.

    Args:
        alpha: opening angle [rad], shape (n_cells,), in (0, pi/2].
        N1: normal force of the type-1 contacts [N], shape (n_cells,), compression positive.
        N2: normal force of the type-2 contacts [N], shape (n_cells,), compression positive.
        T1: tangential force of the type-1 contacts [N], shape (n_cells,), > 0 resists
            opening (spec section 4).
        l1, l2: cell lengths [m], shape (n_cells,).
        kn: normal contact stiffness [N/m] of the pathological contacts.
        diameter: grain diameter D [m].

    Returns:
        (moment, area): moment [N m], shape (n_cells, 2, 2), local frame (index 0 = n,
        1 = t), compression positive; area V_cell [m^2], shape (n_cells,).
    """
    c, s = np.cos(alpha), np.sin(alpha)
    axial = 0.5 * l2 * c / s  # d1 cos a = l1/2 - y2
    d2 = l1 - 2.0 * axial
    moment = np.zeros((np.shape(alpha)[0], 2, 2))
    moment[:, 0, 0] = 4.0 * axial * (N1 * c + T1 * s) + 2.0 * N2 * d2 + kn * np.maximum(diameter - l1, 0.0) * l1
    moment[:, 1, 1] = 2.0 * l2 * (N1 * s - T1 * c) + 2.0 * kn * np.maximum(diameter - l2, 0.0) * l2
    return moment, cell_area(l1, l2, d2)


def observables(
    l1: np.ndarray,
    l2: np.ndarray,
    d1: np.ndarray,
    d2: np.ndarray,
    alpha: np.ndarray,
    N1: np.ndarray,
    N2: np.ndarray,
    T1: np.ndarray,
    moment: np.ndarray,
    area: np.ndarray,
) -> dict[str, np.ndarray]:
    """The H-cell observables of the cell-model protocol, each shape (n_cells,).

    Args:
        l1, l2: axial and lateral cell lengths [m].
        d1, d2: type-1 and type-2 branch lengths [m].
        alpha: opening angle [rad].
        N1, N2, T1: contact forces [N], compression positive, T1 > 0 resists opening.
        moment: Love-Weber moment [N m], shape (n_cells, 2, 2), local frame (n, t).
        area: V_cell [m^2].

    Returns:
        ``l1, l2, d1, d2`` [m], ``alpha_deg`` [deg], ``N1, N2, T1`` [N], ``S_nn, S_tt``
        [N m], ``area`` [m^2], ``closed1, closed2`` (bool: the contact carries a normal
        force) and grain centres ``x_n{i}, x_t{i}`` [m] for labels i = 1..6 (cell centre at
        the origin).
    """
    out = {
        "l1": l1,
        "l2": l2,
        "d1": d1,
        "d2": d2,
        "alpha_deg": np.degrees(alpha),
        "N1": N1,
        "N2": N2,
        "T1": T1,
        "S_nn": moment[:, 0, 0],
        "S_tt": moment[:, 1, 1],
        "area": area,
        "closed1": N1 > 0.0,
        "closed2": N2 > 0.0,
    }
    positions = grain_positions(l1, l2, 0.5 * d2)
    for i in range(N_GRAINS):
        out[f"x_n{i + 1}"] = positions[:, i, 0]
        out[f"x_t{i + 1}"] = positions[:, i, 1]
    return out


def touching_cells(alpha0_deg: float | np.ndarray, n_cells: int, diameter: float) -> tuple[np.ndarray, ...]:
    """Geometry of force-free initial cells: d1 = d2 = D at opening angle alpha0.

    Args:
        alpha0_deg: initial opening angle [deg], scalar or shape (n_cells,), each in
            [30, 90); ValueError (one line) otherwise.
        n_cells: number of cells.
        diameter: grain diameter D [m].

    Returns:
        alpha [rad], l1 [m], l2 [m], each shape (n_cells,).
    """
    alpha0 = np.broadcast_to(np.asarray(alpha0_deg, dtype=np.float64), (int(n_cells),))
    bad = ~((alpha0 >= ALPHA_MIN_DEG) & (alpha0 < ALPHA_MAX_DEG))
    if bad.any():
        check_alpha0_deg(alpha0[bad][0])
    alpha = np.radians(alpha0)
    D = np.full(alpha.shape, float(diameter))
    l1, l2 = lengths(D, D, alpha)
    return alpha, l1, l2
