"""Advance a batch of DEM cells by one strain increment each: Warp and numpy engines.

``DemIntegrator.step(state_in, state_out, d_eps_local)`` launches the cell-step kernel
(``warp_hcell.kernels``); ``launch_step`` is the only code that knows its argument order. On
the CPU the batch is split into contiguous chunks launched from ``threads`` Python threads
(Warp CPU launches release the GIL); every cell is computed by the same code whatever the
chunking, so results are bit-identical for any ``threads``.

``NumpyIntegrator`` performs the same step with numpy, vectorised over cells (substeps in
a Python loop). It is the reference for agreement tests and speed ratios.

Per increment and cell: the driven DOFs follow the cell strain over
n_drive = ceil(max|d_eps| / strain_per_substep) substeps; then substeps continue until the
unbalanced force ratio (largest free-DOF force / max(largest normal force, force_floor))
is <= force_tolerance, or max_substeps. A free grain whose net force is exactly zero is
held at rest: an unloaded grain has no quasi-static reason to move, and Cundall damping
(proportional to the force) could not stop it, so mechanism states would drift.
Strain increments are compression positive: l <- l (1 - d_eps).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from warp_hcell.kernels import step_kernel
from warp_hcell.model import DemModel
from warp_hcell.state import DemState


CHUNKS_PER_THREAD = 4
"""CPU chunks per thread: chunks are taken by the threads as they finish (load balancing)."""
MIN_CELLS_PER_CHUNK = 128
"""Smallest CPU chunk [cells]: smaller batches run in one launch on the calling thread."""


def check_increment(model: DemModel, d_eps_local: np.ndarray) -> np.ndarray:
    """Validate a strain increment: finite, shape (n_cells, 2), within max_substeps.

    Returns:
        ``d_eps_local`` as a C-contiguous float64 array.
    """
    d_eps = np.ascontiguousarray(d_eps_local, dtype=np.float64)
    if d_eps.shape != (model.n_cells, 2):
        raise ValueError(f"d_eps_local has shape {d_eps.shape}, expected ({model.n_cells}, 2)")
    if not np.all(np.isfinite(d_eps)):
        raise ValueError("d_eps_local contains non-finite values")
    largest = float(np.abs(d_eps).max(initial=0.0))
    if largest >= 1.0:
        raise ValueError(f"strain increment {largest:g} must be < 1 in magnitude (l <- l (1 - d_eps))")
    if math.ceil(largest / model.settings.strain_per_substep) > model.settings.max_substeps:
        raise ValueError(f"strain increment {largest:g} is too large for max_substeps = "
                         f"{model.settings.max_substeps} at {model.settings.strain_per_substep:g} per substep")
    return d_eps


def launch_step(model: DemModel, state_in: DemState, state_out: DemState, d_eps_local: wp.array,
                start: int, stop: int) -> None:
    """Launch the cell-step kernel over cells [start, stop) of the batch (whole arrays passed)."""
    settings, law = model.settings, model.contact_law
    kernel = step_kernel(*model.meso.topology_key())
    wp.launch(
        kernel, dim=stop - start,
        inputs=[model.radius, model.inv_mass, model.reference_position, model.reference_cell_size, model.dt,
                model.force_floor, law.kn, law.kt, law.mu, settings.damping, settings.contact_tolerance,
                settings.strain_per_substep, settings.force_tolerance, int(settings.max_substeps),
                state_in.position, state_in.velocity, state_in.shear_force, state_in.cell_size, d_eps_local,
                int(start)],
        outputs=[state_out.position, state_out.velocity, state_out.shear_force, state_out.contact_force,
                 state_out.contact, state_out.cell_size, state_out.substeps, state_out.converged],
        device=model.device)


class DemIntegrator:
    """Warp engine: one kernel launch per chunk of cells.

    Args:
        model: the batch model.
        threads: CPU threads launching chunks in parallel (ignored on CUDA devices).
        pool: an executor with ``threads`` workers to reuse (e.g. across the models of one
            backend); by default the integrator makes its own.
    """

    def __init__(self, model: DemModel, *, threads: int = 2, pool: ThreadPoolExecutor | None = None):
        if int(threads) < 1:
            raise ValueError(f"threads = {threads} must be >= 1")
        self.model = model
        self.threads = 1 if wp.get_device(model.device).is_cuda else int(threads)
        self._pool = None if self.threads == 1 else pool or ThreadPoolExecutor(self.threads)
        # compile/load the kernel here, once, rather than concurrently from the chunk threads
        one = model.take(np.zeros(1, dtype=np.int64))
        scratch = DemState.empty(1, model.meso.n_grains, model.meso.n_pairs, model.device)
        launch_step(one, one.state(), scratch, wp.zeros(1, dtype=wp.vec2d, device=model.device), 0, 1)

    def step(self, state_in: DemState, state_out: DemState, d_eps_local: np.ndarray) -> None:
        """Advance every cell by its strain increment; writes ``state_out`` only.

        Args:
            state_in: cells before the increment (not modified).
            state_out: receives the cells after the increment (same n_cells).
            d_eps_local: (d_eps_n, d_eps_t) [-], shape (n_cells, 2), compression positive.
        """
        model = self.model
        d_eps = wp.array(check_increment(model, d_eps_local), dtype=wp.vec2d, device=model.device)
        n_cells = model.n_cells
        # more chunks than threads, so that the pool balances cells of very different substep
        # counts; no chunk below MIN_CELLS_PER_CHUNK (the thread hand-off would cost more)
        n_chunks = min(CHUNKS_PER_THREAD * self.threads, n_cells // MIN_CELLS_PER_CHUNK)
        if self._pool is None or n_chunks < 2:
            launch_step(model, state_in, state_out, d_eps, 0, n_cells)
            return
        bounds = np.linspace(0, n_cells, n_chunks + 1).astype(int)
        jobs = [self._pool.submit(launch_step, model, state_in, state_out, d_eps, start, stop)
                for start, stop in zip(bounds[:-1], bounds[1:])]
        for job in jobs:
            job.result()


class NumpyIntegrator:
    """Numpy engine of the same step (CPU only), vectorised over cells.

    Args:
        model: the batch model (its device must be the CPU).
    """

    def __init__(self, model: DemModel):
        if wp.get_device(model.device).is_cuda:
            raise ValueError("the numpy DEM engine runs on the CPU only; use device='cpu'")
        self.model = model

    def step(self, state_in: DemState, state_out: DemState, d_eps_local: np.ndarray) -> None:
        """Same contract as ``DemIntegrator.step``."""
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
        cut2 = (rsum * (1.0 + settings.contact_tolerance)) ** 2
        src = state_in.to_numpy()
        x = src["position"].copy()
        v = src["velocity"].copy()
        fs = src["shear_force"].copy()
        l_start = src["cell_size"]
        l_end = np.stack([l_start[:, 0] * (1.0 - d_eps[:, 0]), l_start[:, 1] * (1.0 - d_eps[:, 1])], axis=1)
        n_drive = np.ceil(np.abs(d_eps).max(axis=1) / settings.strain_per_substep).astype(np.int32)
        scale0 = l_start / l_ref
        dscale = (l_end - l_start) / l_ref
        inv_n_drive = 1.0 / np.maximum(n_drive, 1).astype(np.float64)
        n_cells = model.n_cells
        dx = np.zeros_like(x)
        fn = np.zeros_like(fs)
        touch = np.zeros(fs.shape, np.int32)
        substeps = np.zeros(n_cells, np.int32)
        converged = np.zeros(n_cells, np.int32)
        act = np.arange(n_cells)
        while act.size:
            b = x[act][:, pj] - x[act][:, pi]
            dist2 = b[..., 0] ** 2 + b[..., 1] ** 2
            on = dist2 <= cut2[act]
            dist = np.sqrt(np.where(on, dist2, 1.0))
            u = b * (1.0 / dist)[..., None]
            ddx = dx[act][:, pj] - dx[act][:, pi]
            du = ddx[..., 1] * u[..., 0] - ddx[..., 0] * u[..., 1]
            normal = law.kn * np.maximum(rsum[act] - dist, 0.0)
            cap = law.mu * normal
            shear = np.where(on, np.clip(fs[act] + law.kt * du, -cap, cap), 0.0)
            normal = np.where(on, normal, 0.0)
            fs[act], fn[act], touch[act] = shear, normal, on
            f_i = np.stack([-normal * u[..., 0] - shear * u[..., 1], -normal * u[..., 1] + shear * u[..., 0]], -1)
            f_i = np.where(on[..., None], f_i, 0.0)
            force = np.zeros((act.size, meso.n_grains, 2))
            for p in range(meso.n_pairs):  # pair order fixed: same summation order as the kernel
                force[:, pi[p]] += f_i[:, p]
                force[:, pj[p]] -= f_i[:, p]
            fmax = normal.max(axis=1)
            unbalanced = np.abs(np.where(free, force, 0.0)).max(axis=(1, 2))
            checking = substeps[act] >= n_drive[act]
            done = checking & (unbalanced <= settings.force_tolerance * np.maximum(fmax, floor[act]))
            converged[act[done]] = 1
            stop = done | (checking & (substeps[act] >= settings.max_substeps))
            keep = ~stop
            act, force = act[keep], force[keep]
            if not act.size:
                break
            substeps[act] += 1
            s = np.where(substeps[act] < n_drive[act], substeps[act] * inv_n_drive[act], 1.0)
            scale = scale0[act] + dscale[act] * s[:, None]
            x_drive = ref[act] * scale[:, None, :]
            va, xa, ha = v[act], x[act], h[act]
            accel = force * inv_mass[act]
            power = force * (va + 0.5 * ha * accel)
            damped = va + ha * (accel * (1.0 - settings.damping * np.sign(power)))
            unloaded = np.all(force == 0.0, axis=2, keepdims=True)
            v_free = np.where(unloaded, 0.0, damped)
            dx[act] = np.where(free, v_free * ha, x_drive - xa)
            x[act] = np.where(free, xa + v_free * ha, x_drive)
            v[act] = v_free
        v = np.where(free, v, dx / h)  # driven DOFs: the velocity of their last substep
        b = x[:, pj] - x[:, pi]
        u = b / np.linalg.norm(b, axis=-1, keepdims=True)
        contact_force = np.stack([-fn * u[..., 0] - fs * u[..., 1], -fn * u[..., 1] + fs * u[..., 0]], -1)
        out = {"position": x, "velocity": v, "shear_force": fs, "contact_force": contact_force, "contact": touch,
               "cell_size": l_end, "substeps": substeps, "converged": converged}
        for name, value in out.items():
            target = getattr(state_out, name)
            target.assign(np.ascontiguousarray(value, dtype=target.numpy().dtype))
