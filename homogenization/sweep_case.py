"""One case of a sweep: its biaxial test, with the erosion restart where it asks for one, and its summary numbers.

``case_task`` is the task the workers of ``warp_hcell.core.execution`` run (``compute_case``:
no file written); ``run_test`` runs the test on a cell model, in two parts around the removal
of the fines (``warp_hcell.dem.erosion``) when the case erodes; ``summarise`` gives the numbers
of summary.csv (``homogenization.cli.sweep``). Stresses [N/m] and strains [-], compression
positive.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from homogenization import driver, figures, loading
from homogenization.backends import make_cell_model
from homogenization.sweep_plan import Case
from warp_hcell.core.cli import UserError
from warp_hcell.core.parameters import contact_law_from_dict
from warp_hcell.mesostructures.builders import parse_mesostructure
from warp_hcell.mesostructures.mesostructure import Mesostructure

STRAIN_MARKS = (0.05, 0.10, 0.15)
"""eps1 [-] of the p_at_<5|10|15>pct columns."""
SOFTENING_DROP = 0.01
"""Fall of q after a maximum, as a fraction of p0 [-], that makes it the first peak."""
ERODE_STAGE, ERODED_STAGE = "erode", "eroded"
"""Stage labels of the zero-strain removal increment and of the shear after it."""
class _ContinuedCell:
    """A cell model that starts from a given state and scales V_cell so that V0 is a given volume.

    The driver computes V0 from the areas of the initial state and J from the increments it
    applies; a test continued after erosion keeps the V0 J of the first part this way (the
    Love-Weber moments are untouched; observables report the true areas).
    """

    def __init__(self, inner: Any, state: Any, area_scale: float) -> None:
        self.inner = inner
        self.state = state
        self.area_scale = float(area_scale)
        self.name = inner.name

    def init_state(self, mesostructure: Mesostructure, n_cells: int) -> Any:
        if n_cells != self.state.n_cells:
            raise ValueError(f"continued state has {self.state.n_cells} cells, asked for {n_cells}")
        return self.state

    def response(self, state: Any):
        response = self.inner.response(state)
        return dataclasses.replace(response, area=response.area * self.area_scale)

    def step(self, state: Any, d_eps_local: np.ndarray, *, with_tangent: bool = False):
        new, response = self.inner.step(state, d_eps_local, with_tangent=with_tangent)
        return new, dataclasses.replace(response, area=response.area * self.area_scale)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def _join(first: driver.Record, second: driver.Record, programme: loading.Programme) -> driver.Record:
    """One record of a test run in two parts (``second`` continues ``first``)."""
    def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a, b])

    def cat_dict(a: dict, b: dict, n_a: int, n_b: int) -> dict:
        out = {}
        for name in dict.fromkeys([*a, *b]):
            va = a[name] if name in a else np.full((n_a, *np.shape(b[name])[1:]), np.nan)
            vb = b[name] if name in b else np.full((n_b, *np.shape(a[name])[1:]), np.nan)
            out[name] = np.concatenate([np.asarray(va, dtype=np.result_type(va, np.float64)),
                                        np.asarray(vb, dtype=np.result_type(vb, np.float64))])
        return out

    J1 = first.J[-1]
    eps11 = cat(first.eps11, second.eps11 + first.eps11[-1])
    eps22 = cat(first.eps22, second.eps22 + first.eps22[-1])
    J = cat(first.J, second.J * J1)
    return driver.Record(
        stage=cat(first.stage, second.stage), eps11=eps11, eps22=eps22,
        sigma11=cat(first.sigma11, second.sigma11), sigma22=cat(first.sigma22, second.sigma22),
        sigma12=cat(first.sigma12, second.sigma12), p=cat(first.p, second.p), q=cat(first.q, second.q),
        J=J, volume=first.V0 * J, newton_iterations=cat(first.newton_iterations, second.newton_iterations),
        diagnostics=cat_dict(first.diagnostics, second.diagnostics, first.n_increments, second.n_increments),
        snapshot_increment=cat(first.snapshot_increment, second.snapshot_increment + first.n_increments),
        snapshot_stage=cat(first.snapshot_stage, second.snapshot_stage),
        snapshots=cat_dict(first.snapshots, second.snapshots, first.snapshot_increment.size,
                           second.snapshot_increment.size),
        theta_deg=first.theta_deg, weights=first.weights, V0=first.V0, parameters=first.parameters,
        backend=first.backend, programme=programme, final_state=second.final_state,
        step_seconds=cat(first.step_seconds, second.step_seconds))


def run_test(cell_model: Any, case: Case, meso: Mesostructure) -> driver.Record:
    """The biaxial test of ``case`` on ``cell_model`` from cells of ``meso``, with erosion where the case asks for it."""
    prm = case.parameters
    common = dict(mesostructure=meso, n_orientations=prm["n_orientations"], stress_rtol=prm["stress_rtol"],
                  progress=False)
    full = loading.biaxial(case.p0, prm["eps_max"], prm["increment"], iso_increment=prm["iso_increment"],
                           drained=prm["drained"])
    if prm["erode_at"] is None:
        return driver.run(cell_model, full, **common)
    from warp_hcell.dem.erosion import erode_state

    iso, shear = full
    n_before = min(loading.n_increments_for(prm["erode_at"], prm["increment"]), shear.n_increments - 1)
    eps_before = prm["eps_max"] * n_before / shear.n_increments

    def shear_step(eps: float, n: int, label: str) -> loading.Step:
        if prm["drained"]:
            return loading.drained_biaxial(case.p0, eps, n, label=label)
        return loading.constant_volume_biaxial(eps, n, label=label)

    before = (iso, shear_step(eps_before, n_before, shear.label))
    relax = (loading.drained_biaxial(case.p0, 0.0, 1, label=ERODE_STAGE) if prm["drained"]
             else loading.proportional_strain(0.0, 0.0, 1, label=ERODE_STAGE))
    after = (relax,
             shear_step(prm["eps_max"] - eps_before, shear.n_increments - n_before, ERODED_STAGE))
    first = driver.run(cell_model, before, **common)
    state = cell_model.state_from_arrays(first.final_state)
    reduced, reduced_state, _ = erode_state(cell_model, state, [g - 1 for g in prm["eroded_grains"]])
    volume_now = float(first.weights @ reduced.response(reduced_state).area)
    continued = _ContinuedCell(reduced, reduced_state, first.V0 * first.J[-1] / volume_now)
    second = driver.run(continued, after, **common)
    return _join(first, second, before + after)


def summarise(record: driver.Record, p0: float) -> dict[str, float]:
    """Summary numbers of the shear stages of ``record`` (see the module docstring)."""
    curve = figures.shear_curve(record)
    eps1, p, q = curve.eps1[1:], curve.p[1:], curve.q[1:]
    peak = int(np.argmax(q))
    row = {"peak_q": q[peak], "eps1_at_peak": eps1[peak], "p_at_peak": p[peak],
           "p_end": p[-1], "q_end": q[-1], "eps1_end": eps1[-1]}
    for mark in STRAIN_MARKS:
        row[f"p_at_{round(100 * mark)}pct"] = float(np.interp(mark, eps1, p)) if eps1[-1] >= mark - 1e-12 else math.nan
    running = np.maximum.accumulate(q)
    fallen = np.flatnonzero(q < running - SOFTENING_DROP * p0)
    if fallen.size:
        first = int(np.argmax(q[: fallen[0] + 1]))
        row.update(first_peak_q=q[first], eps1_at_first_peak=eps1[first], p_at_first_peak=p[first])
    else:
        row.update(first_peak_q=math.nan, eps1_at_first_peak=math.nan, p_at_first_peak=math.nan)
    unconverged = record.diagnostics.get("n_unconverged")
    row["n_unconverged"] = float(np.nansum(unconverged)) if unconverged is not None else 0.0
    return {k: float(v) for k, v in row.items()}


def compute_case(case: Case) -> driver.Record:
    """The record of one case (no file written): the task a worker runs."""
    prm = case.parameters
    options: dict[str, Any] = dict(prm["backend_options"]) | case.options
    meso = parse_mesostructure(case.source).build(None if math.isnan(case.alpha0) else case.alpha0)
    if "model" in options:
        options["model"] = Path(options["model"])
    model = make_cell_model(case.backend, contact_law=contact_law_from_dict(prm["contact_law"]), radius=prm["radius"], **options)
    return run_test(model, case, meso)


CASE_ERRORS = (driver.ControlError, ValueError, UserError, RuntimeError)
"""Exceptions that fail one case (listed at the end) instead of the sweep."""


def case_task(_shared: Any, case: Case) -> tuple[driver.Record | None, float, str | None]:
    """``warp_hcell.core.execution`` task: (record, wall seconds, None), or (None, seconds, error line)."""
    start = time.perf_counter()
    try:
        record = compute_case(case)
    except CASE_ERRORS as exc:
        return None, time.perf_counter() - start, " ".join(str(exc).split()) or type(exc).__name__
    return record, time.perf_counter() - start, None


