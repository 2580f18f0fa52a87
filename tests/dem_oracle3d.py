"""Numpy engine of the 3D cell step (``warp_hcell.dem.kernels3d``): the reference the Warp kernel must equal bit for bit.

Vectorised over cells, substeps in a Python loop; the same floating-point operations in the same
order as the kernel (sums over grains, axes and pairs in index order; Warp's dot, length and cross
written out as the kernel evaluates them).
"""

from __future__ import annotations

import numpy as np


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def step(arrays: dict, d_eps: np.ndarray, *, pairs: np.ndarray, driven: np.ndarray, faces: np.ndarray,
         law, settings) -> dict[str, np.ndarray]:
    """One increment of every cell.

    Args:
        arrays: ``radius`` (n, g), ``inv_mass`` (n, g), ``reference_position`` (n, g, 3),
            ``reference_cell_size`` (n, 3), ``dt`` (n,), ``force_floor`` (n,), and the state
            ``position`` (n, g, 3), ``velocity`` (n, g, 3), ``shear_force`` (n, p, 3), ``cell_size`` (n, 3).
        d_eps: (n, 3) [-]; pairs (p, 2), driven (g, 3) bool, faces (f, 3): the topology.
        law: ``ContactLaw``; settings: ``DemSettings``.

    Returns:
        The kernel's outputs: position, velocity, shear_force, contact_force, contact, cell_size,
        moment (tension positive), volume, substeps, converged.
    """
    pi, pj = pairs[:, 0], pairs[:, 1]
    n_grains, n_pairs = driven.shape[0], pairs.shape[0]
    free = ~driven
    radius, inv_mass = arrays["radius"], arrays["inv_mass"][:, :, None]
    ref, l_ref = arrays["reference_position"], arrays["reference_cell_size"]
    h = arrays["dt"][:, None, None]
    floor = arrays["force_floor"]
    rsum = radius[:, pi] + radius[:, pj]
    widen = 1.0 + settings.contact_tolerance
    cut2 = (rsum * widen) * (rsum * widen)
    x = arrays["position"].copy()
    v = arrays["velocity"].copy()
    fs = arrays["shear_force"].copy()
    l_start = arrays["cell_size"]
    l_end = l_start * (1.0 - d_eps)
    largest = np.maximum(np.maximum(np.abs(d_eps[:, 0]), np.abs(d_eps[:, 1])), np.abs(d_eps[:, 2]))
    n_phase = np.ceil(largest / settings.strain_per_substep).astype(np.int32)
    scale0 = l_start / l_ref
    dscale = (l_end - l_start) / l_ref
    inv_n_coarse = 1.0 / np.maximum(n_phase, 1).astype(np.float64)
    n_cells = x.shape[0]
    d_new = ref * dscale[:, None, :] * inv_n_coarse[:, None, None]
    dot, norm2, dot_v, norm_v = (np.zeros(n_cells) for _ in range(4))
    for g in range(n_grains):
        for a in range(3):
            if driven[g, a]:
                dot = dot + v[:, g, a] * h[:, 0, 0] * d_new[:, g, a]
                norm2 = norm2 + d_new[:, g, a] * d_new[:, g, a]
                dot_v = dot_v + v[:, g, a] * (ref[:, g, a] * dscale[:, a])
                norm_v = norm_v + v[:, g, a] * v[:, g, a]
    lam = np.where(norm2 > 0.0, dot / np.where(norm2 > 0.0, norm2, 1.0), 0.0)
    off = np.where(driven, np.abs(v * h - lam[:, None, None] * d_new), 0.0).max(axis=(1, 2))
    driving_size = np.where(driven, np.abs(d_new), 0.0).max(axis=(1, 2))
    steady = (lam > 0.0) & (off <= settings.velocity_change * lam * driving_size)
    grown = np.minimum(settings.strain_per_substep, np.maximum(settings.refined_strain_per_substep,
                                                               settings.rate_growth * lam * largest * inv_n_coarse))
    rate = np.where(steady, grown, settings.refined_strain_per_substep)
    n_phase = np.ceil(largest / rate).astype(np.int32)
    ds = np.where(largest > 0.0, rate / np.where(largest > 0.0, largest, 1.0), 0.0)
    span = np.where(steady & (norm_v > 0.0), dot_v / np.where(norm_v > 0.0, norm_v, 1.0), 0.0)
    drift = np.where(free, span[:, None, None] * v, 0.0)
    x_start = x.copy()
    v = np.where(free, 0.0, v)
    s_base, s_now = np.zeros(n_cells), np.zeros(n_cells)
    k_phase, refined = np.zeros(n_cells, np.int32), np.zeros(n_cells, bool)
    last_regime = np.zeros((n_cells, n_pairs))
    dx = np.zeros_like(x)
    substeps = np.zeros(n_cells, np.int32)
    driving_substeps = np.zeros(n_cells, np.int32)
    converged = np.zeros(n_cells, np.int32)
    act = np.arange(n_cells)
    while act.size:
        b = x[act][:, pj] - x[act][:, pi]
        dist2 = _dot(b, b)
        on = dist2 <= cut2[act]
        dist = np.sqrt(np.where(on, dist2, 1.0))
        u = b * (1.0 / dist)[..., None]
        rel = dx[act][:, pj] - dx[act][:, pi]
        du = rel - _dot(rel, u)[..., None] * u
        old = fs[act]
        projected = old - _dot(old, u)[..., None] * u
        before2, after2 = _dot(old, old), _dot(projected, projected)
        carried = np.where((after2 > 0.0)[..., None],
                           projected * np.sqrt(before2 / np.where(after2 > 0.0, after2, 1.0))[..., None], projected)
        overlap = rsum[act] - dist
        normal = law.kn * np.where(overlap > 0.0, overlap, 0.0)
        trial = carried + law.kt * du
        cap = law.mu * normal
        size = np.sqrt(_dot(trial, trial))
        shear = np.where((size > cap)[..., None], trial * (cap / np.where(size > 0.0, size, 1.0))[..., None], trial)
        shear = np.where(on[..., None], shear, 0.0)
        normal = np.where(on, normal, 0.0)
        regime = np.where(on, np.where((normal > 0.0) & (size >= cap), 2.0, 1.0), 0.0)
        changed = (substeps[act, None] > 0) & (regime != last_regime[act])
        last_regime[act] = regime
        fs[act] = shear
        f_i = np.where(on[..., None], shear - normal[..., None] * u, 0.0)
        force = np.zeros((act.size, n_grains, 3))
        for p in range(n_pairs):
            force[:, pi[p]] += f_i[:, p]
            force[:, pj[p]] -= f_i[:, p]
        driving = k_phase[act] < n_phase[act]
        refine = driving & changed.any(axis=1) & ~refined[act]
        if refine.any():
            c = act[refine]
            refined[c] = True
            n_rest = np.ceil((1.0 - s_now[c]) * largest[c] / settings.refined_strain_per_substep).astype(np.int32)
            longer = n_rest > n_phase[c] - k_phase[c]
            c, n_rest = c[longer], n_rest[longer]
            s_base[c], n_phase[c], k_phase[c] = s_now[c], n_rest, 0
            ds[c] = settings.refined_strain_per_substep / largest[c]
        fmax = normal.max(axis=1, initial=0.0)
        unbalanced = np.abs(np.where(free, force, 0.0)).max(axis=(1, 2))
        done = ~driving & (unbalanced <= settings.force_tolerance * np.maximum(fmax, floor[act]))
        converged[act[done]] = 1
        stop = done | (~driving & (substeps[act] >= settings.max_substeps))
        keep = ~stop
        act, force, driving = act[keep], force[keep], driving[keep]
        if not act.size:
            break
        substeps[act] += 1
        s_prev = s_now[act]
        moving = act[driving]
        k_phase[moving] += 1
        driving_substeps[moving] += 1
        s_now[moving] = np.where(k_phase[moving] < n_phase[moving],
                                 np.minimum(s_base[moving] + k_phase[moving] * ds[moving], 1.0), 1.0)
        x_drive = ref[act] * (scale0[act] + dscale[act] * s_now[act][:, None])[:, None, :]
        va, xa, ha = v[act], x[act], h[act]
        accel = force * inv_mass[act]
        power = force * (va + 0.5 * ha * accel)
        damped = va + ha * (accel * (1.0 - settings.damping * np.sign(power)))
        unloaded = np.all(force == 0.0, axis=2, keepdims=True)
        v_free = np.where(unloaded, 0.0, damped)
        move = v_free * ha + np.where(unloaded, 0.0, drift[act] * (s_now[act] - s_prev)[:, None, None])
        dx[act] = np.where(free, move, x_drive - xa)
        x[act] = np.where(free, xa + move, x_drive)
        v[act] = np.where(free, v_free, va)
    spent = driving_substeps.astype(np.float64)[:, None, None] * h
    spent_safe = np.where(spent > 0, spent, 1.0)
    v = np.where(driving_substeps[:, None, None] > 0,
                 np.where(free, (x - x_start) / spent_safe, ref * dscale[:, None, :] / spent_safe), 0.0)
    b = x[:, pj] - x[:, pi]
    dist2 = _dot(b, b)
    dist = np.sqrt(dist2)
    u = b / dist[..., None]
    touching = dist2 <= cut2
    normal = np.where(touching, law.kn * np.maximum(rsum - dist, 0.0), 0.0)
    contact_force = fs - normal[..., None] * u
    moment = np.zeros((n_cells, 3, 3))
    for p in range(n_pairs):
        moment += contact_force[:, p, :, None] * b[:, p, None, :]
    six_volume = np.zeros(n_cells)
    for fa, fb, fc in faces:
        six_volume = six_volume + _dot(x[:, fa], _cross(x[:, fb], x[:, fc]))
    return {"position": x, "velocity": v, "shear_force": fs, "contact_force": contact_force,
            "contact": touching.astype(np.int32), "cell_size": l_end, "moment": moment,
            "volume": np.abs(six_volume) / 6.0, "substeps": substeps, "converged": converged}
