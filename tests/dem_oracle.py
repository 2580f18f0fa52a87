"""The numpy oracle of the DEM cell step: ``NumpyIntegrator``, the reference of the Warp kernel.

It performs the step of ``warp_hcell.dem.kernels`` with numpy, vectorised over cells
(substeps in a Python loop), with the same floating-point operations in the same order, so
that tests compare the kernel with it to round-off and benchmarks time it beside the kernel
(``benchmarks/bench_dem_kernel.py``). CPU only.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import warp as wp

from warp_hcell.dem.integrator import check_increment
from warp_hcell.dem.model import DemModel
from warp_hcell.dem.state import DemState
from warp_hcell.mesostructures import hcell


class NumpyIntegrator:
    """The DEM step with numpy (CPU only), vectorised over cells.

    Args:
        model: the batch model (its device must be the CPU).
    """

    def __init__(self, model: DemModel):
        if wp.get_device(model.device).is_cuda:
            raise ValueError("the numpy DEM engine runs on the CPU only; use device='cpu'")
        self.model = model

    def step(self, state_in: DemState, state_out: DemState, d_eps_local: np.ndarray) -> None:
        """Same contract as ``DemIntegrator.step``; the same floating-point operations, in the same order."""
        model = self.model
        d_eps = check_increment(model, d_eps_local)
        meso = model.meso
        arrays = {name: getattr(model, name).numpy() for name in
                  ("radius", "inv_mass", "reference_position", "reference_cell_size", "dt", "force_floor")}
        src = state_in.to_numpy()
        arrays.update({name: src[name] for name in ("position", "velocity", "shear_force", "cell_size")})
        out = step_cells(arrays, d_eps, pairs=meso.pairs, driven=meso.driven, law=model.contact_law,
                         settings=model.settings, inner=_inner, pair_law=_pair_law, pair_force=_pair_force,
                         cell_volume=lambda x: _area(x, meso.outer))
        out["area"] = out.pop("volume")
        for name, value in out.items():
            target = getattr(state_out, name)
            target.assign(np.ascontiguousarray(value, dtype=target.numpy().dtype))


def _inner(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _pair_law(fs: np.ndarray, overlap: np.ndarray, u: np.ndarray, rel: np.ndarray, on: np.ndarray, law):
    du = rel[..., 1] * u[..., 0] - rel[..., 0] * u[..., 1]
    normal = law.kn * np.maximum(overlap, 0.0)
    cap = law.mu * normal
    shear = np.where(on, np.clip(fs + law.kt * du, -cap, cap), 0.0)
    normal = np.where(on, normal, 0.0)
    regime = np.where(on, np.where((normal > 0.0) & (np.abs(shear) >= law.mu * normal), 2.0, 1.0), 0.0)
    f_i = np.stack([-normal * u[..., 0] - shear * u[..., 1], -normal * u[..., 1] + shear * u[..., 0]], -1)
    return shear, normal, regime, np.where(on[..., None], f_i, 0.0)


def _pair_force(fs: np.ndarray, normal: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.stack([-normal * u[..., 0] - fs * u[..., 1], -normal * u[..., 1] + fs * u[..., 0]], -1)


def _area(x: np.ndarray, outer: np.ndarray) -> np.ndarray:
    twice_area = np.zeros(x.shape[0])
    for a, b_next in zip(outer, np.roll(outer, -1)):
        twice_area = twice_area + (x[:, a, 0] * x[:, b_next, 1] - x[:, b_next, 0] * x[:, a, 1])
    return 0.5 * np.abs(twice_area)


def step_cells(arrays: dict, d_eps: np.ndarray, *, pairs: np.ndarray, driven: np.ndarray, law, settings,
               inner: Callable, pair_law: Callable, pair_force: Callable, cell_volume: Callable) -> dict[str, np.ndarray]:
    """One increment of every cell of either dimension: the stepping shared by the kernels of both
    (``warp_hcell.dem.stepping``), the pairs and the volume given per dimension.

    Args:
        arrays: ``radius`` (n, g), ``inv_mass`` (n, g), ``reference_position`` (n, g, dim),
            ``reference_cell_size`` (n, dim), ``dt`` (n,), ``force_floor`` (n,), and the state
            ``position`` (n, g, dim), ``velocity`` (n, g, dim), ``shear_force`` (n, p) in 2D,
            (n, p, 3) in 3D, ``cell_size`` (n, dim).
        d_eps: (n, dim) [-]; pairs (p, 2), driven (g, dim) bool: the topology.
        law: ``ContactLaw``; settings: ``DemSettings``.
        inner: the dot product over the last axis, written out as the kernel evaluates it.
        pair_law: ``(shear_old, overlap, u, relative_move, on, law)`` -> (shear, normal, regime,
            force on grain i) of every pair (unit vectors u from i to j).
        pair_force: ``(shear, normal, u)`` -> the contact forces (n, p, dim) written out.
        cell_volume: ``(position)`` -> the cell volume (area in 2D) (n,).

    Returns:
        The kernel's outputs: position, velocity, shear_force, contact_force, contact, cell_size,
        moment (tension positive), volume, substeps, converged.
    """
    pi, pj = pairs[:, 0], pairs[:, 1]
    n_grains, n_pairs = driven.shape[0], pairs.shape[0]
    dim = driven.shape[1]
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
    largest = np.abs(d_eps).max(axis=1)
    n_phase = np.ceil(largest / settings.strain_per_substep).astype(np.int32)
    scale0 = l_start / l_ref
    dscale = (l_end - l_start) / l_ref
    inv_n_coarse = 1.0 / np.maximum(n_phase, 1).astype(np.float64)
    n_cells = x.shape[0]
    d_new = ref * dscale[:, None, :] * inv_n_coarse[:, None, None]
    dot, norm2, dot_v, norm_v = (np.zeros(n_cells) for _ in range(4))
    for g in range(n_grains):
        for a in range(dim):
            if driven[g, a]:
                dot = dot + v[:, g, a] * h[:, 0, 0] * d_new[:, g, a]
                norm2 = norm2 + d_new[:, g, a] * d_new[:, g, a]
                dot_v = dot_v + v[:, g, a] * (ref[:, g, a] * dscale[:, a])
                norm_v = norm_v + v[:, g, a] * v[:, g, a]
    lam = np.where(norm2 > 0.0, dot / np.where(norm2 > 0.0, norm2, 1.0), 0.0)
    off = np.where(driven, np.abs(v * h - lam[:, None, None] * d_new), 0.0).max(axis=(1, 2))
    driving_size = np.where(driven, np.abs(d_new), 0.0).max(axis=(1, 2))
    steady = (lam > 0.0) & (off <= settings.velocity_change * lam * driving_size)
    grown = np.minimum(settings.strain_per_substep, np.maximum(settings.closing_rate,
                                                               settings.rate_growth * lam * largest * inv_n_coarse))
    rate = np.where(steady, grown, settings.refined_strain_per_substep)
    n_phase = np.ceil(largest / rate).astype(np.int32)
    ds = np.where(largest > 0.0, rate / np.where(largest > 0.0, largest, 1.0), 0.0)
    span = np.where(steady & (norm_v > 0.0), dot_v / np.where(norm_v > 0.0, norm_v, 1.0), 0.0)
    drift = np.where(free, span[:, None, None] * v, 0.0)
    x_start = x.copy()
    v = np.where(free, 0.0, v)
    s_base, s_now = np.zeros(n_cells), np.zeros(n_cells)
    k_phase, refined = np.zeros(n_cells, np.int32), np.zeros(n_cells, np.int32)
    closures = np.zeros(n_cells, bool)
    last_regime = np.zeros((n_cells, n_pairs))
    dx = np.zeros_like(x)
    substeps = np.zeros(n_cells, np.int32)
    driving_substeps = np.zeros(n_cells, np.int32)
    converged = np.zeros(n_cells, np.int32)
    act = np.arange(n_cells)
    while act.size:
        b = x[act][:, pj] - x[act][:, pi]
        dist2 = inner(b, b)
        on = dist2 <= cut2[act]
        dist = np.sqrt(np.where(on, dist2, 1.0))
        u = b * (1.0 / dist)[..., None]
        rel = dx[act][:, pj] - dx[act][:, pi]
        shear, normal, regime, f_i = pair_law(fs[act], rsum[act] - dist, u, rel, on, law)
        changed = (substeps[act, None] > 0) & (regime != last_regime[act])
        closed = (changed & (last_regime[act] == 0.0)).any(axis=1)
        closures[act] |= closed
        last_regime[act] = regime
        fs[act] = shear
        force = np.zeros((act.size, n_grains, dim))
        for p in range(n_pairs):
            force[:, pi[p]] += f_i[:, p]
            force[:, pj[p]] -= f_i[:, p]
        driving = k_phase[act] < n_phase[act]
        level = np.where(closed, 2, np.where(changed.any(axis=1), 1, 0))
        refine = driving & (level > refined[act])
        if refine.any():
            c = act[refine]
            refined[c] = level[refine]
            rate = np.where(refined[c] == 2, settings.closing_rate, settings.refined_strain_per_substep)
            n_rest = np.ceil((1.0 - s_now[c]) * largest[c] / rate).astype(np.int32)
            longer = n_rest > n_phase[c] - k_phase[c]
            c, n_rest, rate = c[longer], n_rest[longer], rate[longer]
            s_base[c], n_phase[c], k_phase[c] = s_now[c], n_rest, 0
            ds[c] = rate / largest[c]
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
    closing = closures[:, None, None]
    v_driven = np.where(closing, ref * dscale[:, None, :] * ds[:, None, None] / h, ref * dscale[:, None, :] / spent_safe)
    v = np.where(driving_substeps[:, None, None] > 0,
                 np.where(free, np.where(closing, 0.0, (x - x_start) / spent_safe), v_driven), 0.0)
    b = x[:, pj] - x[:, pi]
    dist2 = inner(b, b)
    dist = np.sqrt(dist2)
    u = b / dist[..., None]
    touching = dist2 <= cut2
    normal = np.where(touching, law.kn * np.maximum(rsum - dist, 0.0), 0.0)
    contact_force = pair_force(fs, normal, u)
    moment = np.zeros((n_cells, dim, dim))
    for p in range(n_pairs):
        moment += contact_force[:, p, :, None] * b[:, p, None, :]
    return {"position": x, "velocity": v, "shear_force": fs, "contact_force": contact_force,
            "contact": touching.astype(np.int32), "cell_size": l_end, "moment": moment,
            "volume": cell_volume(x), "substeps": substeps, "converged": converged}


def h_cell_model(alpha0_deg, n_cells: int, radius: float, **options) -> DemModel:
    """A ``DemModel`` of H-cells with per-cell opening angles [deg] (scalar or (n_cells,)),
    vectorised (``hcell.reference``): no ``Mesostructure`` per cell. ``options`` go to
    ``DemModel.from_reference`` (contact_law, settings, device)."""
    alpha0_deg = np.broadcast_to(np.asarray(alpha0_deg, dtype=np.float64), (n_cells,))
    position, cell_size = hcell.reference(alpha0_deg, radius)
    template = hcell.h_cell(float(alpha0_deg[0]), radius)
    return DemModel.from_reference(template, np.broadcast_to(template.radius, (n_cells, template.n_grains)),
                                   position, cell_size, **options)
