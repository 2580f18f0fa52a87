"""Advance a batch of DEM cells by one strain increment each: the launcher of the Warp step kernel.

``DemIntegrator.step(state_in, state_out, d_eps_local)`` launches the cell-step kernel
(``warp_hcell.dem.kernels``); ``launch_step`` is the only code that knows its argument order. On
the CPU the batch is split into contiguous chunks launched from ``threads`` Python threads
(Warp CPU launches release the GIL); every cell is computed by the same code whatever the
chunking, so results are bit-identical for any ``threads``.

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

from warp_hcell.dem.dimensions import DIMENSIONS
from warp_hcell.dem.laws import warp_law
from warp_hcell.dem.model import DemModel
from warp_hcell.dem.state import DemState
from warp_hcell.dem.stepping import cell_vector


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
              model.force_floor, *warp_law(law.name).kernel_constants(law), settings.damping,
              settings.contact_tolerance,
              settings.strain_per_substep, settings.refined_strain_per_substep,
              settings.closing_rate, settings.velocity_change,
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
    return DIMENSIONS[model.meso.dim].kernel(model.meso, model.contact_law.name)


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
    """One kernel launch per chunk of cells.

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
        self._d_eps = wp.zeros(model.n_cells, dtype=cell_vector(model.meso.dim), device=model.device)
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
