"""Consistent tangent of a quasi-static few-grain cell by static condensation (any mesostructure).

``condensed_tangent`` returns C = d(S_aa)/d(d_eps_b) [N m] of a batch of cells at equilibrium from
their grain positions, contact forces and driven-DOF mask only (nothing here knows the shape of a
cell); vectorised over cells (numpy).

The maths (spec section 13), tension-positive DEM forces, pair p = (i, j), branch b = x_j - x_i,
``d = |b|``, u = b / d, tangent projector P = I - u u^T (2D: P = w w^T, w = (-u_t, u_n)):

- the force on grain i by grain j is f = -N u + T, N = kn (r_i + r_j - d), T the tangential
  spring force; its stiffness k_p = df/db = kn u u^T - (N / d) P - u T^T / d + dT/db, with
  dT/db = kt P (stick) or -mu kn t u^T + kt (P - t t^T) (slide, t = T / norm(T)); pairs without
  overlap carry nothing;
- a contact slides when its elastic trial force exceeds the cap,
  ``|T_old + kt (b_new - b_old) . w_mid| > mu N`` (``sliding_contacts``);
- K = dF/dx = -sum_p (e_j - e_i)(e_j - e_i)^T (x) k_p; free DOFs stay in equilibrium
  (pseudo-inverse of K_ff, so a DOF without stiffness stays at rest), hence
  dF_d = (K_dd - K_df K_ff^+ K_fd) dx_d;
- at equilibrium S_aa = sum_g F_g,a x_g,a over driven DOFs (compression positive), and with
  dx_d = B d_eps: dS_aa/d d_eps_b = sum (dF_g,a/d d_eps_b x_g,a + F_g,a dx_g,a/d d_eps_b).

Hertz-Mindlin (spatial cells, ``law="hertz-mindlin"``): kn, kt are the pair constants kh, ks
[N/m^1.5] (``warp_hcell.core.laws.hertz_mindlin.pair_constants``, broadcasting against
(n_cells, n_pairs)), N = kh delta^(3/2), and kn, kt above become the tangent stiffnesses
1.5 kh sqrt(delta) and ks sqrt(delta).
"""

from __future__ import annotations

import functools

import numpy as np

from warp_hcell.core.contact import PairLaw, normal_force


def _unit_tangent(branch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal ``u = b / |b|`` and tangent w = (-u_t, u_n), each shape (..., 2)."""
    u = branch / np.linalg.norm(branch, axis=-1)[..., None]
    return u, np.stack([-u[..., 1], u[..., 0]], axis=-1)


def require_planar_law(law: str) -> None:
    """ValueError (one line) unless ``law`` (a contact-law name) is the linear law, the one law of planar cells."""
    if law != "linear":
        raise ValueError(f"the {law} contact law is defined for spatial cells only")


def sliding_contacts(position_old: np.ndarray, position: np.ndarray, radius: np.ndarray, pairs: np.ndarray,
                     shear_force_old: np.ndarray, *, kn: float, kt: float, mu: float,
                     law: str = "linear") -> np.ndarray:
    """Contacts whose elastic trial force over the increment exceeds the Coulomb cap.

    Args:
        position_old, position: grain centres before and after the increment [m], shape
            (n_cells, n_grains, 2).
        radius: grain radii [m], shape (n_cells, n_grains).
        pairs: candidate pairs (i, j), shape (n_pairs, 2).
        shear_force_old: tangential force before the increment [N], shape (n_cells, n_pairs).
        kn, kt: contact stiffnesses [N/m]; mu: friction coefficient [-].
        law: contact-law name; planar cells carry the linear law only (``require_planar_law``).

    Returns:
        bool, shape (n_cells, n_pairs): overlapping pairs with ``|T_old + kt (b - b_old) . w_mid| > mu N``.
    """
    require_planar_law(law)
    i, j = pairs[:, 0], pairs[:, 1]
    b_old = position_old[:, j] - position_old[:, i]
    b = position[:, j] - position[:, i]
    _, w_mid = _unit_tangent(b_old + b)
    trial = shear_force_old + kt * np.sum((b - b_old) * w_mid, axis=-1)
    N = normal_force(radius[:, i] + radius[:, j] - np.linalg.norm(b, axis=-1), kn)
    return (N > 0.0) & (np.abs(trial) > mu * N)


def contact_stiffness(branch: np.ndarray, overlap: np.ndarray, shear_force: np.ndarray, sliding: np.ndarray, *,
                      kn: float, kt: float, mu: float, law: str = "linear") -> np.ndarray:
    """Stiffness df/db of every pair [N/m], shape (n_cells, n_pairs, 2, 2) (``law``: the linear law only,
    ``require_planar_law``).

    Args:
        branch: b = x_j - x_i [m], shape (n_cells, n_pairs, 2).
        overlap: ``r_i + r_j - |b|`` [m], shape (n_cells, n_pairs); pairs with overlap <= 0
            carry no force and no stiffness.
        shear_force: tangential force T [N] along w = (-u_t, u_n), shape (n_cells, n_pairs).
        sliding: True where the contact slides (T = +-mu N), shape (n_cells, n_pairs).
        kn, kt: normal and tangential contact stiffness [N/m]; mu: friction coefficient [-].
    """
    require_planar_law(law)
    d = np.linalg.norm(branch, axis=-1)
    u, w = _unit_tangent(branch)
    active = overlap > 0.0
    N = normal_force(overlap, kn)
    T = np.where(active, shear_force, 0.0)
    sliding = active & sliding
    # dT/db = kt w (stick) or -sign(T) mu kn u (slide): dT = a u + c w
    a = np.where(sliding, -np.copysign(mu * kn, T), 0.0)
    c = np.where(sliding, 0.0, kt)
    # k = kn u u^T - (N / d) w w^T - (T / d) u w^T + w (a u + c w)^T
    kuu, kww, kuw, kwu = np.where(active, kn, 0.0), np.where(active, c - N / d, 0.0), -T / d, np.where(active, a, 0.0)
    k = np.empty(branch.shape[:-1] + (2, 2))
    for r in range(2):
        for s in range(2):
            k[..., r, s] = (kuu * u[..., r] * u[..., s] + kww * w[..., r] * w[..., s] + kuw * u[..., r] * w[..., s]
                            + kwu * w[..., r] * u[..., s])
    return k


def sliding_contacts_3d(position_old: np.ndarray, position: np.ndarray, radius: np.ndarray, pairs: np.ndarray,
                        shear_force_old: np.ndarray, *, kn: float, kt: float, mu: float,
                        law: str = "linear") -> np.ndarray:
    """``sliding_contacts`` of spatial cells: the old spring (n_cells, n_pairs, 3) carried into the
    mid-increment tangent plane (projected, rescaled to its magnitude) plus kt times the tangential
    relative displacement; True where that trial exceeds mu N. ``law``: module docstring (the
    Hertz-Mindlin kt: the mean of the increment, ``PairLaw.move_stiffness``)."""
    i, j = pairs[:, 0], pairs[:, 1]
    b_old = position_old[:, j] - position_old[:, i]
    b = position[:, j] - position[:, i]
    mid = b_old + b
    u = mid / np.linalg.norm(mid, axis=-1, keepdims=True)
    projected = shear_force_old - np.sum(shear_force_old * u, axis=-1, keepdims=True) * u
    before, after = np.linalg.norm(shear_force_old, axis=-1), np.linalg.norm(projected, axis=-1)
    carried = projected * np.where(after > 0.0, before / np.where(after > 0.0, after, 1.0), 0.0)[..., None]
    step = b - b_old
    overlap = radius[:, i] + radius[:, j] - np.linalg.norm(b, axis=-1)
    pair = PairLaw(law, kn, kt)
    if law != "linear":  # the mean kt of the increment
        start_overlap = radius[:, i] + radius[:, j] - np.linalg.norm(b_old, axis=-1)
        kt = pair.move_stiffness(start_overlap, overlap)[..., None]
    trial = carried + kt * (step - np.sum(step * u, axis=-1, keepdims=True) * u)
    N = pair.normal(overlap)
    return (N > 0.0) & (np.linalg.norm(trial, axis=-1) > mu * N)


def contact_stiffness_3d(branch: np.ndarray, overlap: np.ndarray, shear_force: np.ndarray, sliding: np.ndarray, *,
                         kn: float, kt: float, mu: float, law: str = "linear") -> np.ndarray:
    """``contact_stiffness`` of spatial cells, shape (n_cells, n_pairs, 3, 3) (module docstring).

    ``shear_force`` is the tangential force vector on grain i, shape (n_cells, n_pairs, 3); ``law``:
    module docstring.
    """
    d = np.linalg.norm(branch, axis=-1)
    u = branch / d[..., None]
    active = overlap > 0.0
    pair = PairLaw(law, kn, kt)
    N = pair.normal(overlap)
    if law != "linear":
        kn, kt = pair.normal_stiffness(overlap)[..., None, None], pair.shear_stiffness(overlap)[..., None, None]
    T = np.where(active[..., None], shear_force, 0.0)
    size = np.linalg.norm(T, axis=-1)
    t = T / np.where(size > 0.0, size, 1.0)[..., None]
    eye = np.eye(3)
    uu = u[..., :, None] * u[..., None, :]
    P = eye - uu
    slide = (active & sliding)[..., None, None]
    dT = np.where(slide, -mu * kn * t[..., :, None] * u[..., None, :] + kt * (P - t[..., :, None] * t[..., None, :]),
                  kt * P)
    k = kn * uu - (N / d)[..., None, None] * P - u[..., :, None] * T[..., None, :] / d[..., None, None] + dT
    return np.where(active[..., None, None], k, 0.0)


@functools.lru_cache(maxsize=32)
def _assembly(pairs: tuple[tuple[int, int], ...], n_grains: int, dim: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(e_j - e_i) of every pair (i, j), shape (n_pairs, n_grains), and the matrix mapping the
    pair stiffnesses k[p, a, b] (flattened) to the DOF stiffness
    K[(g, a), (h, b)] = -sum_p (e_j - e_i)_g (e_j - e_i)_h k[p, a, b] (flattened), shape
    (dim^2 n_pairs, (dim n_grains)^2): one matrix product per batch instead of an einsum. Built once
    per topology (read-only arrays)."""
    index = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    incidence = np.zeros((index.shape[0], n_grains))
    incidence[np.arange(index.shape[0]), index[:, 1]] = 1.0
    incidence[np.arange(index.shape[0]), index[:, 0]] = -1.0
    eye = np.eye(dim)
    assembly = -np.einsum("pg,ph,ac,bd->pabgchd", incidence, incidence, eye, eye).reshape(dim * dim * index.shape[0], -1)
    incidence.flags.writeable = False
    assembly.flags.writeable = False
    return incidence, assembly


def pair_forces(branch: np.ndarray, overlap: np.ndarray, shear_force: np.ndarray, *, kn: float, kt: float,
                law: str = "linear") -> np.ndarray:
    """Force on grain i of every planar pair [N], -f_n u + f_s w, shape (n_cells, n_pairs, 2); pairs with
    overlap <= 0 carry none (``contact_stiffness``: the arguments)."""
    active = overlap > 0.0
    u, w = _unit_tangent(branch)
    return -kn * np.where(active, overlap, 0.0)[..., None] * u + np.where(active, shear_force, 0.0)[..., None] * w


def pair_forces_3d(branch: np.ndarray, overlap: np.ndarray, shear_force: np.ndarray, *, kn: float, kt: float,
                   law: str = "linear") -> np.ndarray:
    """``pair_forces`` of spatial pairs, -f_n u + f_s, shape (n_cells, n_pairs, 3) (``contact_stiffness_3d``:
    the arguments)."""
    active = overlap > 0.0
    u = branch / np.linalg.norm(branch, axis=-1, keepdims=True)
    normal = kn * np.where(active, overlap, 0.0) if law == "linear" else PairLaw(law, kn, kt).normal(overlap)
    return -normal[..., None] * u + np.where(active[..., None], shear_force, 0.0)


PAIR_TERMS = {2: (contact_stiffness, pair_forces), 3: (contact_stiffness_3d, pair_forces_3d)}
"""(pair stiffness df/db, pair force) of each dimension, as ``condensed_tangent`` assembles them."""


def condensed_tangent(position: np.ndarray, radius: np.ndarray, pairs: np.ndarray, driven: np.ndarray,
                      shear_force: np.ndarray, sliding: np.ndarray, drive_rate: np.ndarray, *, kn: float,
                      kt: float, mu: float, law: str = "linear") -> np.ndarray:
    """Consistent tangent of cells at quasi-static equilibrium, by static condensation.

    Args:
        position: grain centres [m], (n_cells, n_grains, dim), local frame.
        radius: grain radii [m], (n_cells, n_grains).
        pairs: candidate contact pairs (i, j), 0-based, (n_pairs, 2).
        driven: True where DOF (grain, direction) follows the cell strain, (n_grains, dim).
        shear_force: tangential spring force on grain i [N], tension-positive: (n_cells, n_pairs)
            along w in 2D, (n_cells, n_pairs, 3) in 3D.
        sliding: True where the contact slides, (n_cells, n_pairs) (``sliding_contacts``).
        drive_rate: dx_g,a / d d_eps_a [m] of driven DOFs (0 elsewhere), (n_cells, n_grains, dim).
        kn, kt: contact stiffnesses [N/m]; mu: friction coefficient [-].
        law: contact-law name; "hertz-mindlin": kn, kt are kh, ks [N/m^1.5] (module docstring).

    Returns:
        C = d(S_aa)/d(d_eps_b) [N m], (n_cells, dim, dim), compression positive; row = stress
        component, column = strain component."""
    position = np.asarray(position, dtype=np.float64)
    n_cells, n_grains, dim = position.shape
    n_dof = dim * n_grains
    i, j = pairs[:, 0], pairs[:, 1]
    branch = position[:, j] - position[:, i]
    overlap = radius[:, i] + radius[:, j] - np.linalg.norm(branch, axis=-1)
    stiffness, forces = PAIR_TERMS[dim]
    k = stiffness(branch, overlap, shear_force, sliding, kn=kn, kt=kt, mu=mu, law=law)
    incidence, assembly = _assembly(tuple(map(tuple, np.asarray(pairs).tolist())), n_grains, dim)
    k_flat = k.reshape(n_cells, -1)
    d_mask = np.asarray(driven, dtype=bool).reshape(-1)
    fi, di = np.flatnonzero(~d_mask), np.flatnonzero(d_mask)

    def block(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """K[:, rows][:, :, cols], assembled directly."""
        return (k_flat @ assembly[:, (rows[:, None] * n_dof + cols).reshape(-1)]).reshape(n_cells, rows.size, cols.size)

    # net contact force on every DOF, F = -sum_p (e_j - e_i) f_p
    f = forces(branch, overlap, shear_force, kn=kn, kt=kt, law=law)
    F = -(np.swapaxes(f, 1, 2) @ incidence).transpose(0, 2, 1).reshape(n_cells, n_dof)

    K_dd = block(di, di)
    K_c = K_dd - block(di, fi) @ np.linalg.pinv(block(fi, fi)) @ block(fi, di) if fi.size else K_dd
    # driven kinematics: dx_d = B d_eps, B[dof(g, a), a] = drive_rate[g, a]
    rate = np.asarray(drive_rate, dtype=np.float64).reshape(n_cells, n_dof)[:, di]
    component = np.tile(np.arange(dim), n_grains)[di]
    B = rate[:, :, None] * (component[None, :, None] == np.arange(dim)[None, None, :])
    dF = K_c @ B  # (n_cells, n_driven, dim)
    x = position.reshape(n_cells, n_dof)[:, di]
    C = np.empty((n_cells, dim, dim))
    for a in range(dim):
        on_a = component == a
        C[:, a, :] = (np.einsum("cd,cdb->cb", x[:, on_a], dF[:, on_a]) + np.einsum("cd,cdb->cb", F[:, di][:, on_a], B[:, on_a]))
    return C
