"""The numpy oracle of the DEM cell step: ``NumpyIntegrator``, the reference of the Warp kernel.

It performs the step of ``warp_hcell.dem.kernels`` with numpy, vectorised over cells
(substeps in a Python loop), with the same floating-point operations in the same order, so
that tests compare the kernel with it to round-off and benchmarks time it beside the kernel
(``benchmarks/bench_dem_kernel.py``). CPU only.
"""

from __future__ import annotations

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
        model, law, settings = self.model, self.model.contact_law, self.model.settings
        d_eps = check_increment(model, d_eps_local)
        meso = model.meso
        pi, pj = meso.pairs[:, 0], meso.pairs[:, 1]
        free = ~meso.driven  # (n_grains, 2)
        radius = model.radius.numpy()
        inv_mass = model.inv_mass.numpy()[:, :, None]
        ref = model.reference_position.numpy()
        l_ref = model.reference_cell_size.numpy()
        h = model.dt.numpy()[:, None, None]
        floor = model.force_floor.numpy()
        rsum = radius[:, pi] + radius[:, pj]
        widen = 1.0 + settings.contact_tolerance
        cut2 = (rsum * widen) * (rsum * widen)
        src = state_in.to_numpy()
        x = src["position"].copy()
        v = src["velocity"].copy()
        fs = src["shear_force"].copy()
        l_start = src["cell_size"]
        l_end = np.stack([l_start[:, 0] * (1.0 - d_eps[:, 0]), l_start[:, 1] * (1.0 - d_eps[:, 1])], axis=1)
        largest = np.maximum(np.abs(d_eps[:, 0]), np.abs(d_eps[:, 1]))
        n_phase = np.ceil(largest / settings.strain_per_substep).astype(np.int32)
        scale0 = l_start / l_ref
        dscale = (l_end - l_start) / l_ref
        inv_n_coarse = 1.0 / np.maximum(n_phase, 1).astype(np.float64)
        driven = meso.driven
        # strain per substep and predictor from the cell's state (see the kernel): same sums, same order
        d_new = ref * dscale[:, None, :] * inv_n_coarse[:, None, None]
        d_last = v * h
        n_cells = model.n_cells
        dot, norm2, dot_v, norm_v = (np.zeros(n_cells) for _ in range(4))
        for g in range(meso.n_grains):
            for k in range(2):
                if driven[g, k]:
                    dot = dot + d_last[:, g, k] * d_new[:, g, k]
                    norm2 = norm2 + d_new[:, g, k] * d_new[:, g, k]
                    dot_v = dot_v + v[:, g, k] * (ref[:, g, k] * dscale[:, k])
                    norm_v = norm_v + v[:, g, k] * v[:, g, k]
        lam = np.where(norm2 > 0.0, dot / np.where(norm2 > 0.0, norm2, 1.0), 0.0)
        off = np.where(driven, np.abs(d_last - lam[:, None, None] * d_new), 0.0).max(axis=(1, 2))
        drive = np.where(driven, np.abs(d_new), 0.0).max(axis=(1, 2))
        steady = (lam > 0.0) & (off <= settings.velocity_change * lam * drive)
        grown = np.minimum(settings.strain_per_substep,
                           np.maximum(settings.refined_strain_per_substep, settings.rate_growth * lam * largest * inv_n_coarse))
        rate = np.where(steady, grown, settings.refined_strain_per_substep)
        n_phase = np.ceil(largest / rate).astype(np.int32)
        ds = np.where(largest > 0.0, rate / np.where(largest > 0.0, largest, 1.0), 0.0)
        span = np.where(steady & (norm_v > 0.0), dot_v / np.where(norm_v > 0.0, norm_v, 1.0), 0.0)
        drift = np.where(free, span[:, None, None] * v, 0.0)
        x_start = x.copy()
        v = np.where(free, 0.0, v)  # free grains start at rest
        s_base, s_now = np.zeros(n_cells), np.zeros(n_cells)
        k_phase, refined = np.zeros(n_cells, np.int32), np.zeros(n_cells, bool)
        last_regime = np.zeros(fs.shape)
        dx = np.zeros_like(x)
        fn = np.zeros_like(fs)
        touch = np.zeros(fs.shape, np.int32)
        substeps = np.zeros(n_cells, np.int32)
        driving_substeps = np.zeros(n_cells, np.int32)
        converged = np.zeros(n_cells, np.int32)
        act = np.arange(n_cells)
        while act.size:
            b = x[act][:, pj] - x[act][:, pi]
            dist2 = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1]
            on = dist2 <= cut2[act]
            dist = np.sqrt(np.where(on, dist2, 1.0))
            u = b * (1.0 / dist)[..., None]
            ddx = dx[act][:, pj] - dx[act][:, pi]
            du = ddx[..., 1] * u[..., 0] - ddx[..., 0] * u[..., 1]
            normal = law.kn * np.maximum(rsum[act] - dist, 0.0)
            cap = law.mu * normal
            shear = np.where(on, np.clip(fs[act] + law.kt * du, -cap, cap), 0.0)
            normal = np.where(on, normal, 0.0)
            regime = np.where(on, np.where((normal > 0.0) & (np.abs(shear) >= law.mu * normal), 2.0, 1.0), 0.0)
            changed = (substeps[act, None] > 0) & (regime != last_regime[act])
            last_regime[act] = regime
            fs[act], fn[act], touch[act] = shear, normal, on
            f_i = np.stack([-normal * u[..., 0] - shear * u[..., 1], -normal * u[..., 1] + shear * u[..., 0]], -1)
            f_i = np.where(on[..., None], f_i, 0.0)
            force = np.zeros((act.size, meso.n_grains, 2))
            for p in range(meso.n_pairs):  # pair order fixed: same summation order as the kernel
                force[:, pi[p]] += f_i[:, p]
                force[:, pj[p]] -= f_i[:, p]
            # adaptive driving (see the kernel)
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
            fmax = normal.max(axis=1)
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
            scale = scale0[act] + dscale[act] * s_now[act][:, None]
            x_drive = ref[act] * scale[:, None, :]
            va, xa, ha = v[act], x[act], h[act]
            accel = force * inv_mass[act]
            power = force * (va + 0.5 * ha * accel)
            damped = va + ha * (accel * (1.0 - settings.damping * np.sign(power)))
            unloaded = np.all(force == 0.0, axis=2, keepdims=True)
            v_free = np.where(unloaded, 0.0, damped)
            move = v_free * ha + np.where(unloaded, 0.0, drift[act] * (s_now[act] - s_prev)[:, None, None])
            dx[act] = np.where(free, move, x_drive - xa)
            x[act] = np.where(free, xa + move, x_drive)
            v[act] = v_free
        # every grain: mean velocity over the increment's driving substeps
        spent = driving_substeps.astype(np.float64)[:, None, None] * h
        spent_safe = np.where(spent > 0, spent, 1.0)
        v = np.where(driving_substeps[:, None, None] > 0,
                     np.where(free, (x - x_start) / spent_safe, ref * dscale[:, None, :] / spent_safe), 0.0)
        b = x[:, pj] - x[:, pi]
        dist = np.sqrt(b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1])
        u = b / dist[..., None]
        contact_force = np.stack([-fn * u[..., 0] - fs * u[..., 1], -fn * u[..., 1] + fs * u[..., 0]], -1)
        moment = np.zeros((n_cells, 2, 2))
        for p in range(meso.n_pairs):  # same summation order as the kernel
            moment += contact_force[:, p, :, None] * b[:, p, None, :]
        twice_area = np.zeros(n_cells)
        outer = meso.outer
        for a, b_next in zip(outer, np.roll(outer, -1)):
            twice_area = twice_area + (x[:, a, 0] * x[:, b_next, 1] - x[:, b_next, 0] * x[:, a, 1])
        out = {"position": x, "velocity": v, "shear_force": fs, "contact_force": contact_force, "contact": touch,
               "cell_size": l_end, "moment": moment, "area": 0.5 * np.abs(twice_area), "substeps": substeps,
               "converged": converged}
        for name, value in out.items():
            target = getattr(state_out, name)
            target.assign(np.ascontiguousarray(value, dtype=target.numpy().dtype))


def h_cell_model(alpha0_deg, n_cells: int, radius: float, **options) -> DemModel:
    """A ``DemModel`` of H-cells with per-cell opening angles [deg] (scalar or (n_cells,)),
    vectorised (``hcell.reference``): no ``Mesostructure`` per cell. ``options`` go to
    ``DemModel.from_reference`` (contact_law, settings, device)."""
    alpha0_deg = np.broadcast_to(np.asarray(alpha0_deg, dtype=np.float64), (n_cells,))
    position, cell_size = hcell.reference(alpha0_deg, radius)
    template = hcell.h_cell(float(alpha0_deg[0]), radius)
    return DemModel.from_reference(template, np.broadcast_to(template.radius, (n_cells, template.n_grains)),
                                   position, cell_size, **options)
