"""The generator's tasks: pure functions of their inputs, run by any execution (``warp_hcell.core.execution``).

- ``explore_starts(inputs, group)``: the exploration trees of the start cells ``group``
  (``warp_hcell.database.exploration.explore``);
- ``probe_chunk(inputs, c)``: the samples of chunk c (``warp_hcell.database.probing.compute_chunk``).

The inputs (``Physics``, ``ExploreInputs``, ``ProbeInputs``) are picklable values, sent
once per worker (``ProbeInputs`` carries the explored states, ~30 MB for the H-cell); each
worker process builds its DEM cell and probe context once per run (cached by the run's
token). A cell's DEM result does not depend on its batch, so a task's result depends
on its inputs and index only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from warp_hcell.database.exploration import explore, WalkProgress
from warp_hcell.mesostructures.files import from_description
from warp_hcell.core.parameters import CellDefaults, ContactLaw, DatabaseSettings, DemSettings
from warp_hcell.database.probing import compute_chunk, ProbeContext


@dataclass(frozen=True)
class Physics:
    """The DEM of a run: contact law, mesostructure (``describe`` text), numerics, device, threads."""

    contact_law: ContactLaw
    mesostructure: str
    dem_settings: DemSettings
    device: str = "cpu"
    threads: int = 1


@dataclass(frozen=True)
class ExploreInputs:
    """Inputs of ``explore_starts``: the physics, the start cells (``describe`` texts), settings, and
    what wraps each walk's increment loop (``warp_hcell.database.exploration.Explorer``; picklable
    for Dask; None: silent)."""

    physics: Physics
    starts: tuple[str, ...]
    settings: DatabaseSettings
    progress: WalkProgress | None = None


@dataclass(frozen=True, eq=False)
class ProbeInputs:
    """Inputs of ``probe_chunk``: the physics, settings, seed and the explored states.

    Attributes:
        token: identifies the run (workers cache their probe context by it).
        states: the exploration states (``warp_hcell.database.exploration.explore``).
    """

    token: str
    physics: Physics
    settings: DatabaseSettings
    seed: int
    states: Mapping[str, np.ndarray]


_CACHE: dict[str, Any] = {}


def dem_cell(physics: Physics):
    """The DEM cell of ``physics``, built once per process."""
    key = ("cell", physics)
    if _CACHE.get("cell_key") != key:
        from warp_hcell.dem.cell import DemCell  # noqa: PLC0415 (Warp loads only where cells are stepped)

        _CACHE.update(cell_key=key, cell=DemCell(physics.contact_law, CellDefaults.radius, settings=physics.dem_settings,
                                                 device=physics.device, threads=physics.threads))
    return _CACHE["cell"]


def explore_starts(inputs: ExploreInputs, group: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Exploration states of the start cells ``group`` explored as one batch (``explore``: the
    states do not depend on the grouping), with the start cell's parameters (e.g. ``alpha0_deg``) and the stop-rule
    counts ``stops.<rule>`` of each state's start cell (int64, per state: the arrays split by
    start cell)."""
    from warp_hcell.dem.cell import DemCellState  # noqa: PLC0415
    from warp_hcell.dem.model import DemModel  # noqa: PLC0415

    physics = inputs.physics
    meso = from_description(physics.mesostructure)
    starts = [from_description(inputs.starts[k]) for k in group]
    model = DemModel.build(starts, len(starts), contact_law=physics.contact_law, settings=physics.dem_settings,
                           device=physics.device)
    states, stops = explore(dem_cell(physics), DemCellState(model, model.state()), meso.schema(), inputs.settings,
                            physics.contact_law, physics.dem_settings.contact_tolerance, np.asarray(group),
                            progress=inputs.progress)
    for name in meso.parameters:
        value = {k: s.parameters[name] for k, s in zip(group, starts)}
        states[name] = np.array([value[k] for k in states["start_id"]], dtype=np.float64)
    index = np.searchsorted(np.asarray(group), states["start_id"])
    states.update({f"stops.{rule}": count[index] for rule, count in stops.items()})
    return states


def probe_context(inputs: ProbeInputs) -> ProbeContext:
    """The probe context of a run, built once per process (cached by ``inputs.token``)."""
    if _CACHE.get("context_token") != inputs.token:
        states = inputs.states
        physics = inputs.physics
        meso = from_description(physics.mesostructure)
        _CACHE.update(context_token=inputs.token, context=ProbeContext(
            cell_model=dem_cell(physics), meso=meso, schema=meso.schema(), states=states,
            contact_law=physics.contact_law, contact_tolerance=physics.dem_settings.contact_tolerance))
    return _CACHE["context"]


def probe_chunk(inputs: ProbeInputs, chunk: int) -> dict[str, np.ndarray]:
    """The samples of chunk ``chunk`` (``compute_chunk``)."""
    return compute_chunk(probe_context(inputs), inputs.settings, inputs.seed, chunk)
