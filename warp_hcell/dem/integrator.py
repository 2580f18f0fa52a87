"""Advance a batch of DEM cells by one strain increment each: Warp and numpy engines.

``DemIntegrator.step(state_in, state_out, d_eps_local)`` launches the cell-step kernel
(``warp_hcell.dem.kernels``); ``launch_step`` is the only code that knows its argument order. On
the CPU the batch is split into contiguous chunks launched from ``threads`` Python threads
(Warp CPU launches release the GIL); every cell is computed by the same code whatever the
chunking, so results are bit-identical for any ``threads``.

``NumpyIntegrator`` performs the same step with numpy, vectorised over cells (substeps in
a Python loop). It is the reference for agreement tests and speed ratios.

Per increment and cell: the driven DOFs follow the cell strain over ceil(max|d_eps| / rate)
substeps, the rate adapted to the cell's state (``warp_hcell.dem.kernels``: between
refined_strain_per_substep and strain_per_substep); then substeps continue until the
unbalanced force ratio (largest free-DOF force / max(largest normal force, force_floor))
is <= force_tolerance, or max_substeps. The kernel also returns the Love-Weber sum and the
outer-polygon area of each cell. A free grain whose net force is exactly zero is
held at rest: an unloaded grain has no quasi-static reason to move, and Cundall damping
(proportional to the force) could not stop it, so mechanism states would drift.
Strain increments are compression positive: l <- l (1 - d_eps).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from warp_hcell.dem.kernels import step_kernel
from warp_hcell.dem.kernels3d import step_kernel_3d
from warp_hcell.dem.model import DemModel
from warp_hcell.dem.state import DemState


CHUNKS_PER_THREAD = 4
"""Most CPU chunks per thread: chunks are taken by the threads as they finish (load balancing)."""
MIN_CELLS_PER_CHUNK = 1024
"""Cells per chunk beyond one chunk per thread: more chunks than threads only where every chunk
keeps this many cells (each extra chunk costs a hand-off, ~15-30 us, for balancing cells of
very different substep counts)."""
MIN_CELLS_TO_SPLIT = 1024
"""Smallest batch [cells] split into one chunk per thread; smaller batches run in one launch on
the calling thread. Measured (docs/dem_stepping.md): handing a chunk to a second thread costs
~100 us per call (thread wake-up and GIL hand-overs), and saves at most half the kernel time
when the second core is free; the kernel of 360 cells at 3-15 substeps takes 100-300 us."""


def check_increment(model: DemModel, d_eps_local: np.ndarray) -> np.ndarray:
    """Validate a strain increment: finite, shape (n_cells, dim), within max_substeps.

    Returns:
        ``d_eps_local`` as a C-contiguous float64 array.
    """
    d_eps = np.ascontiguousarray(d_eps_local, dtype=np.float64)
    dim = model.meso.dim
    if d_eps.shape != (model.n_cells, dim):
        raise ValueError(f"d_eps_local has shape {d_eps.shape}, expected ({model.n_cells}, {dim})")
    if not np.all(np.isfinite(d_eps)):
        raise ValueError("d_eps_local contains non-finite values")
    largest = float(np.abs(d_eps).max(initial=0.0))
    if largest >= 1.0:
        raise ValueError(f"strain increment {largest:g} must be < 1 in magnitude (l <- l (1 - d_eps))")
    finest = model.settings.refined_strain_per_substep
    if math.ceil(largest / finest) > model.settings.max_substeps:
        raise ValueError(f"strain increment {largest:g} is too large for max_substeps = "
                         f"{model.settings.max_substeps} at {finest:g} per substep")
    return d_eps


STATE_IN = ("position", "velocity", "shear_force", "cell_size")
"""State fields read by the kernel, in argument order."""
STATE_OUT = ("position", "velocity", "shear_force", "contact_force", "contact", "cell_size", "moment", "area",
             "substeps", "converged")
"""State fields written by the kernel, in argument order."""


def step_arguments(model: DemModel, state_in: DemState, state_out: DemState, d_eps_local: wp.array,
                   start: int) -> tuple[list, list]:
    """Kernel inputs and outputs for cells [start, start + launch dim) (whole arrays passed)."""
    settings, law = model.settings, model.contact_law
    inputs = [model.radius, model.inv_mass, model.reference_position, model.reference_cell_size, model.dt,
              model.force_floor, law.kn, law.kt, law.mu, settings.damping, settings.contact_tolerance,
              settings.strain_per_substep, settings.refined_strain_per_substep, settings.velocity_change,
              settings.rate_growth,               settings.force_tolerance,
              int(settings.max_substeps), *(getattr(state_in, f) for f in STATE_IN), d_eps_local, int(start)]
    return inputs, [getattr(state_out, f) for f in STATE_OUT]


def launch_step(model: DemModel, state_in: DemState, state_out: DemState, d_eps_local: wp.array,
                start: int, stop: int) -> None:
    """Launch the cell-step kernel over cells [start, stop) of the batch (whole arrays passed)."""
    inputs, outputs = step_arguments(model, state_in, state_out, d_eps_local, start)
    wp.launch(kernel_of(model), dim=stop - start, inputs=inputs, outputs=outputs, device=model.device)


def kernel_of(model: DemModel) -> wp.Kernel:
    """The compiled cell-step kernel of the model's topology."""
    if model.meso.dim == 3:
        return step_kernel_3d(*model.meso.topology_key(), tuple(map(tuple, model.meso.outer.tolist())))
    return step_kernel(*model.meso.topology_key(), tuple(int(g) for g in model.meso.outer))


class _RecordedLaunch:
    """A launch of cells [start, stop) whose constant arguments are packed once.

    Per step only the state arrays are re-packed (the increment lives in a buffer of the
    integrator): packing all 35 kernel arguments costs more than stepping a few hundred cells
    by a few substeps.
    """

    def __init__(self, model: DemModel, state_in: DemState, state_out: DemState, d_eps_local: wp.array,
                 start: int, stop: int):
        inputs, outputs = step_arguments(model, state_in, state_out, d_eps_local, start)
        # argument indices of what changes per step: state-in arrays and d_eps come before first_cell
        self.n_inputs = len(inputs)
        self.command = wp.launch(kernel_of(model), dim=stop - start, inputs=inputs, outputs=outputs,
                                 device=model.device, record_cmd=True)
        self.cpu = wp.get_device(model.device).is_cpu

    def __call__(self, state_in: DemState, state_out: DemState) -> None:
        command, n_inputs = self.command, self.n_inputs
        first = n_inputs - 2 - len(STATE_IN)
        if self.cpu:
            # the arrays' own ctypes structs: no per-argument type checks and conversions
            # (their types were checked when the launch was recorded; DemState fixes them)
            for k, name in enumerate(STATE_IN):
                command.set_param_at_index_from_ctype(first + k, getattr(state_in, name).__ctype__())
            for k, name in enumerate(STATE_OUT):
                command.set_param_at_index_from_ctype(n_inputs + k, getattr(state_out, name).__ctype__())
        else:
            for k, name in enumerate(STATE_IN):
                command.set_param_at_index(first + k, getattr(state_in, name))
            for k, name in enumerate(STATE_OUT):
                command.set_param_at_index(n_inputs + k, getattr(state_out, name))
        command.launch()


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
        self._d_eps = wp.zeros(model.n_cells, dtype=wp.vec2d if model.meso.dim == 2 else wp.vec3d, device=model.device)
        self._d_eps_host = None if wp.get_device(model.device).is_cuda else self._d_eps.numpy()
        # one chunk per thread from MIN_CELLS_TO_SPLIT cells; more chunks than threads, so that
        # the pool balances cells of very different substep counts, where each keeps
        # MIN_CELLS_PER_CHUNK cells
        n_chunks = min(CHUNKS_PER_THREAD * self.threads, model.n_cells // MIN_CELLS_PER_CHUNK)
        if model.n_cells >= MIN_CELLS_TO_SPLIT:
            n_chunks = max(n_chunks, self.threads)
        if self._pool is None or n_chunks < 2:
            self._bounds = [(0, model.n_cells)]
        else:
            edges = np.linspace(0, model.n_cells, n_chunks + 1).astype(int)
            self._bounds = list(zip(edges[:-1].tolist(), edges[1:].tolist()))
        # compile/load the kernel and pack the constant arguments here, once, rather than
        # concurrently from the chunk threads
        initial = model.state()
        scratch = DemState.empty(model.n_cells, model.meso.n_grains, model.meso.n_pairs, model.device, model.meso.dim)
        self._launches = [_RecordedLaunch(model, initial, scratch, self._d_eps, start, stop)
                          for start, stop in self._bounds]

    def step(self, state_in: DemState, state_out: DemState, d_eps_local: np.ndarray) -> None:
        """Advance every cell by its strain increment; writes ``state_out`` only.

        Args:
            state_in: cells before the increment (not modified).
            state_out: receives the cells after the increment (same n_cells).
            d_eps_local: (d_eps_n, d_eps_t[, d_eps_t2]) [-], shape (n_cells, dim), compression positive.
        """
        d_eps = check_increment(self.model, d_eps_local)
        if self._d_eps_host is None:
            self._d_eps.assign(d_eps)
        else:
            np.copyto(self._d_eps_host, d_eps)
        if len(self._launches) == 1:
            self._launches[0](state_in, state_out)
            return
        if len(self._launches) <= self.threads:
            # one chunk per thread: the calling thread runs the first (one hand-off fewer, each
            # ~30 us or more on a loaded machine)
            jobs = [self._pool.submit(launch, state_in, state_out) for launch in self._launches[1:]]
            self._launches[0](state_in, state_out)
        else:
            jobs = [self._pool.submit(launch, state_in, state_out) for launch in self._launches]
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
        if model.meso.dim != 2:
            raise ValueError("the numpy DEM engine steps planar cells; 3D cells run on the Warp engine")
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
