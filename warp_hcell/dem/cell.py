"""Meso-DEM cell backend: batched few-grain DEM cells (Warp kernels) behind the CellModel protocol.

``DemCell(contact_law, radius, *, settings=DemSettings(), device="cpu", threads=2)``
advances every cell of a batch by its own strain increment with the quasi-static DEM of
``warp_hcell.dem`` (one Warp thread per cell). ``init_state(mesostructure, n_cells)`` builds the
cells from any mesostructure, or from one per cell of one topology; the state keeps the
topology (``DemCellState.model.meso``) and ``state_to_arrays`` writes it out, so that
``state_from_arrays`` needs nothing else.

Sign convention: compression and contraction positive. The DEM's tension-positive
Love-Weber sum is converted in ``warp_hcell.dem.love_weber.to_compression_positive`` only. V_cell is the area of the
polygon through the centres of the outer (driven) grains: the hexagon for the H-cell.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from itertools import combinations
from dataclasses import dataclass, fields, replace
from typing import Any, Mapping, Sequence

import numpy as np
import warp as wp

from warp_hcell.core.contact import pair_law
from warp_hcell.core.contract import CellResponse
from warp_hcell.core.dimension import dimension
from warp_hcell.dem.dimensions import DIMENSIONS
from warp_hcell.dem.integrator import DemIntegrator
from warp_hcell.dem.love_weber import to_compression_positive
from warp_hcell.mesostructures.files import with_declarations
from warp_hcell.mesostructures.mesostructure import (
    TOPOLOGY_ARRAYS,
    TOPOLOGY_FIELDS,
    Mesostructure,
    evaluate_observables,
    topology_arrays,
)
from warp_hcell.dem.model import DemModel
from warp_hcell.core.parameters import HERTZ_DT_OVERLAP, check_positive, DemSettings, Law
from warp_hcell.dem.state import DemState, StatePool
from warp_hcell.dem.tangent import condensed_tangent

_MODEL_ARRAYS = ("radius", "reference_position", "reference_cell_size")
TANGENT_CHUNK = 8192
"""Cells per chunk of the condensed tangent, the chunks spread over the backend's threads (numpy
releases the GIL); a cell's tangent does not depend on the chunking."""


@dataclass(frozen=True, eq=False)
class DemCellState:
    """A batch of DEM cells: its immutable model (per-cell reference geometry) and its state."""

    model: DemModel
    dem: DemState

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return self.model.n_cells


class DemCell:
    """Meso-DEM backend (see the module docstring).

    Args:
        contact_law: stiffnesses and friction (any law of ``warp_hcell.core.parameters.CONTACT_LAWS``;
            the Hertz-Mindlin law in spatial cells only).
        radius: grain radius r [m]; positive, not used: every grain's radius comes from
            the mesostructure given to ``init_state`` (the argument keeps the constructor
            of every backend alike, ``homogenization.backends.make_cell_model``).
        settings: DEM numerical settings.
        device: Warp device ("cpu", "cuda:0").
        threads: CPU chunks launched in parallel (results do not depend on it).
    """

    name = "dem"

    def __init__(self, contact_law: Law, radius: float, *, settings: DemSettings = DemSettings(),
                 device: str = "cpu", threads: int = 2):
        if int(threads) < 1:
            raise ValueError(f"threads = {threads} must be >= 1")
        self.contact_law = contact_law
        self.radius = check_positive("radius", radius)
        self.settings = settings
        self.device = str(device)
        self.threads = int(threads)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self._last_integrator: DemIntegrator | None = None
        self._outputs: StatePool | None = None

    # -- construction ---------------------------------------------------------------------
    def _integrator(self, model: DemModel) -> DemIntegrator:
        """The integrator of ``model`` (the last one is kept with its pool of output states:
        trial steps and the following increments reuse them)."""
        integrator = self._last_integrator
        if integrator is None or integrator.model is not model:
            integrator = DemIntegrator(model, threads=self.threads, pool=self._pool)
            self._outputs = StatePool(model.n_cells, model.meso.n_grains, model.meso.n_pairs, model.device,
                                      dim=model.meso.dim)
            self._last_integrator = integrator
        return integrator

    # -- CellModel protocol ---------------------------------------------------------------
    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int) -> DemCellState:
        """Touching, force-free cells of ``mesostructure`` (one, or one per cell of one topology)."""
        model = DemModel.build(mesostructure, int(n_cells), contact_law=self.contact_law, settings=self.settings,
                               device=self.device)
        return DemCellState(model, model.state())

    def step(self, state: DemCellState, d_eps_local: np.ndarray, *,
             with_tangent: bool = False) -> tuple[DemCellState, CellResponse]:
        """Advance every cell by (d_eps_n, d_eps_t[, d_eps_t2]) [-], shape (n_cells, dim), compression positive.

        Pure: ``state`` is not modified. Cells that reach max_substeps without equilibrium are
        counted in ``diagnostics["n_unconverged"]`` and reported with a warning. With
        ``with_tangent`` the response carries d(S_nn, S_tt)/d(d_eps_n, d_eps_t) [N m] of the
        equilibrium reached (``warp_hcell.dem.tangent.condensed_tangent``).
        """
        model = state.model
        integrator = self._integrator(model)
        out = self._outputs.acquire()
        integrator.step(state.dem, out, d_eps_local)
        new = DemCellState(model, out)
        response = self.response(new)
        if with_tangent:
            response = replace(response, tangent=self.step_tangent(state, new))
        if response.diagnostics["n_unconverged"]:
            warnings.warn(f"DEM: {response.diagnostics['n_unconverged']:g} of {model.n_cells} cells did not reach "
                          f"equilibrium within max_substeps = {self.settings.max_substeps}", RuntimeWarning,
                          stacklevel=2)
        return new, response

    @staticmethod
    def at_rest(state: DemCellState) -> DemCellState:
        """``state`` with its velocity memory zero and its model's settings ``DemSettings.from_rest``: stepped,
        it starts from rest, as a state no step produced (``DemState.velocity``; the free grains are not
        predicted and the rate starts from rest_strain_per_substep, ``warp_hcell.dem.kernels``). The database
        probes every state so (``warp_hcell.database.probing``, canonical form).

        Pure: ``state`` is not modified; the other fields are shared with it (a step never writes
        its input), and so is its model where its settings are already those from rest.
        """
        model = state.model
        rest = model.settings.from_rest
        if rest is not model.settings:
            model = replace(model, settings=rest)
        return DemCellState(model, replace(state.dem, velocity=wp.zeros_like(state.dem.velocity)))

    def step_tangent(self, old: DemCellState, new: DemCellState) -> np.ndarray:
        """The tangent ``step(old, d_eps, with_tangent=True)`` returns, of the step from ``old`` to ``new``
        (``new`` = ``step(old, d_eps)``): d(S_aa)/d(d_eps_b) [N m], shape (n_cells, dim, dim), condensed
        (``warp_hcell.dem.tangent.condensed_tangent``; driven DOFs move as x_ref l_old / l_ref per unit strain).
        Computed in chunks of ``TANGENT_CHUNK`` cells on the backend's threads."""
        model, law = new.model, self.contact_law
        arrays, before = new.dem.to_numpy(), old.dem.to_numpy()
        radius_all, pairs, driven = model.radius.numpy(), model.meso.pairs, model.meso.driven
        slides = DIMENSIONS[model.meso.dim].sliding_contacts
        l_ratio = before["cell_size"] / model.reference_cell_size.numpy()
        reference = model.reference_position.numpy()

        def chunk(cells: slice) -> np.ndarray:
            radius = radius_all[cells]
            pair = pair_law(law, radius[:, pairs[:, 0]], radius[:, pairs[:, 1]])
            laws = dict(kn=pair.kn, kt=pair.kt, mu=law.mu)
            position, shear = arrays["position"][cells], arrays["shear_force"][cells]
            sliding = slides(before["position"][cells], position, radius, pairs, before["shear_force"][cells],
                             law=law.name, **laws)
            drive_rate = -reference[cells] * l_ratio[cells, None, :] * driven[None]
            return condensed_tangent(position, radius, pairs, driven, shear, sliding, drive_rate, law=law.name, **laws)

        starts = range(0, max(model.n_cells, 1), TANGENT_CHUNK)
        chunks = [slice(start, start + TANGENT_CHUNK) for start in starts]
        if self._pool is None or len(chunks) < 2:
            return np.concatenate([chunk(cells) for cells in chunks])
        return np.concatenate(list(self._pool.map(chunk, chunks)))

    def response(self, state: DemCellState) -> CellResponse:
        """Love-Weber moment (compression positive) and V_cell of ``state``; diagnostics of its step
        (a law other than the linear one adds ``n_stiffer_than_dt``, ``stiffer_than_dt``)."""
        dem = state.dem  # the step's Love-Weber sum and polygon area, computed in the kernel
        substeps = dem.substeps.numpy()
        diagnostics = {"substeps": float(substeps.sum()), "max_substeps": float(substeps.max(initial=0)),
                       "n_unconverged": float(np.count_nonzero(dem.converged.numpy() == 0))}
        if state.model.contact_law.name != "linear":
            diagnostics["n_stiffer_than_dt"] = float(np.count_nonzero(stiffer_than_dt(state)))
        return CellResponse(moment=to_compression_positive(dem.moment.numpy()), area=dem.area.numpy().copy(),
                            diagnostics=diagnostics)

    def observables(self, state: DemCellState) -> dict[str, np.ndarray]:
        """Per-cell quantities, shape (n_cells,) each, named by the cell's frame (``Dimension.frame``:
        (n, t) or (n, t1, t2)).

        Cell sizes ``l1 .. ld`` [m], ``area`` (V_cell [m^2] or [m^3]), the moment's diagonal
        ``S_nn, S_tt`` (3D: ``S_nn, S_t1t1, S_t2t2``) then its upper triangle ``S_nt`` (3D:
        ``S_nt1, S_nt2, S_t1t2``) [N m] (compression positive), ``n_contacts`` (closed contacts),
        ``substeps`` and ``converged`` of the last step, the observables the mesostructure
        declares (``Mesostructure.observables``), and grain centres ``x_n{i}, x_t{i}`` (3D:
        ``x_n{i}, x_t1{i}, x_t2{i}``) [m] (i = 1-based label).
        """
        arrays = state.dem.to_numpy()
        meso = state.model.meso
        response = self.response(state)
        x, moment, frame = arrays["position"], response.moment, dimension(meso.dim).frame
        obs: dict[str, np.ndarray] = {f"l{k + 1}": arrays["cell_size"][:, k].copy() for k in range(meso.dim)}
        obs["area"] = response.area
        obs.update({f"S_{a}{a}": moment[:, k, k] for k, a in enumerate(frame)})
        obs.update({f"S_{frame[i]}{frame[j]}": moment[:, i, j] for i, j in combinations(range(meso.dim), 2)})
        obs.update({"n_contacts": arrays["contact"].sum(axis=1), "substeps": arrays["substeps"].copy(),
                    "converged": arrays["converged"] == 1})
        if meso.observables:
            branch = x[:, meso.pairs[:, 1]] - x[:, meso.pairs[:, 0]]
            unit = branch / np.hypot.reduce(branch, axis=-1)[..., None]
            normal = 0.0 - np.sum(arrays["contact_force"] * unit, axis=-1)
            obs.update(evaluate_observables(meso, x, normal, arrays["shear_force"], arrays["contact"]))
        for g in range(meso.n_grains):
            for axis, name in enumerate(frame):
                obs[f"x_{name}{g + 1}"] = x[:, g, axis].copy()
        return obs

    def take(self, state: DemCellState, index: np.ndarray) -> DemCellState:
        """Cells ``state[index]`` (int array, repetition allowed), model included."""
        index = np.asarray(index, dtype=np.int64)
        arrays = {k: v[index] for k, v in state.dem.to_numpy().items()}
        model = state.model.take(index)
        return DemCellState(model, DemState.from_numpy(arrays, model.device))

    def state_to_arrays(self, state: DemCellState) -> dict[str, np.ndarray]:
        """Every state array, the per-cell reference geometry and the topology (first axis n_cells)."""
        arrays = {k: np.array(v) for k, v in state.dem.to_numpy().items()}
        arrays.update({k: np.array(getattr(state.model, k).numpy()) for k in _MODEL_ARRAYS})
        arrays.update(topology_arrays(state.model.meso, state.n_cells))
        return arrays

    def state_from_arrays(self, arrays: Mapping[str, Any]) -> DemCellState:
        """Inverse of ``state_to_arrays``; the topology template is rebuilt from the first cell."""
        arrays = {k: np.asarray(arrays[k])
                  for k in (*_MODEL_ARRAYS, *TOPOLOGY_ARRAYS, *(f.name for f in fields(DemState)))}
        meso = with_declarations(Mesostructure(
            name=f"{arrays['radius'].shape[1]}-grain cell from state arrays", radius=arrays["radius"][0],
            position=arrays["reference_position"][0], cell_size=arrays["reference_cell_size"][0],
            **{field: arrays[name][0] for name, field in TOPOLOGY_FIELDS.items()}))
        model = DemModel.from_reference(meso, arrays["radius"], arrays["reference_position"],
                                        arrays["reference_cell_size"], contact_law=self.contact_law,
                                        settings=self.settings, device=self.device)
        return DemCellState(model, DemState.from_numpy(arrays, self.device))


def stiffer_than_dt(state: DemCellState) -> np.ndarray:
    """bool (n_cells,): cells with a contact whose overlap exceeds HERTZ_DT_OVERLAP (r_i + r_j), so stiffer
    than the stiffness their time step was set for (``reference_stiffness`` of ``warp_hcell.dem.laws``)."""
    pairs = state.model.meso.pairs
    x, radius = state.dem.position.numpy(), state.model.radius.numpy()
    rsum = radius[:, pairs[:, 0]] + radius[:, pairs[:, 1]]
    overlap = rsum - np.linalg.norm(x[:, pairs[:, 1]] - x[:, pairs[:, 0]], axis=-1)
    return (overlap > HERTZ_DT_OVERLAP * rsum).any(axis=1)
