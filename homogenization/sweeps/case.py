"""One case of a sweep: its biaxial test, with the removal of the fines where it asks for one, and its summary numbers.

``case_task`` is the task the workers of ``warp_hcell.core.execution`` run (``compute_case``:
no file written); ``run_test`` runs the test on a cell model, one run that removes the fines
(``warp_hcell.dem.erosion``) from its cells between the first shear and the erosion step when
the case erodes (the macro volume V0 J carries on); ``summarise`` gives the numbers
of summary.csv (``homogenization.cli.sweep``). Stresses [N/m] and strains [-], compression
positive.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.output import figures
from homogenization.backends import make_cell_model
from homogenization.element_test.points import MaterialPoints
from homogenization.sweeps.plan import Case
from warp_hcell.core.errors import UserError
from warp_hcell.core.execution import task_warnings
from warp_hcell.core.parameters import contact_law_from_dict
from warp_hcell.mesostructures.builders import parse_mesostructure
from warp_hcell.mesostructures.mesostructure import Mesostructure

STRAIN_MARKS = (0.05, 0.10, 0.15)
"""eps1 [-] of the p_at_<5|10|15>pct columns."""
SOFTENING_DROP = 0.01
"""Fall of q after a maximum, as a fraction of p0 [-], that makes it the first peak."""
ERODE_STAGE, ERODED_STAGE = "erode", "eroded"
"""Stage labels of the zero-strain removal increment and of the shear after it."""


def run_test(cell_model: Any, case: Case, meso: Mesostructure) -> driver.Record:
    """The biaxial test of ``case`` on ``cell_model`` from cells of ``meso``, with erosion where the case asks for it."""
    prm = case.parameters
    common = dict(mesostructure=meso, n_orientations=prm["n_orientations"], stress_rtol=prm["stress_rtol"],
                  progress=False)
    full = programmes.biaxial(case.p0, prm["eps_max"], prm["increment"], iso_increment=prm["iso_increment"],
                           drained=prm["drained"])
    if prm["erode_at"] is None:
        return driver.run(cell_model, full, **common)
    from warp_hcell.dem.erosion import erode_state

    iso, shear = full
    n_before = min(programmes.n_increments_for(prm["erode_at"], prm["increment"]), shear.n_increments - 1)
    eps_before = prm["eps_max"] * n_before / shear.n_increments

    def shear_step(eps: float, n: int, label: str) -> programmes.Step:
        if prm["drained"]:
            return programmes.drained_biaxial(case.p0, eps, n, label=label)
        return programmes.constant_volume_biaxial(eps, n, label=label)

    before = (iso, shear_step(eps_before, n_before, shear.label))
    relax = (programmes.drained_biaxial(case.p0, 0.0, 1, label=ERODE_STAGE) if prm["drained"]
             else programmes.proportional_strain(0.0, 0.0, 1, label=ERODE_STAGE))
    after = (relax,
             shear_step(prm["eps_max"] - eps_before, shear.n_increments - n_before, ERODED_STAGE))

    def erode(points: MaterialPoints) -> None:
        reduced, cells, _ = erode_state(points.model, points.state.cells, [g - 1 for g in prm["eroded_grains"]])
        points.replace_cells(reduced, cells)

    return driver.run(cell_model, before + after, before_stage={len(before): erode}, **common)


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


def fired_counts(record: driver.Record) -> str:
    """The backend's counts of ``record`` summed over its increments, ``NAME=VALUE`` joined by ``;``: every ``n_*``
    diagnostic but ``n_unconverged`` (a column of its own) and the ``*_all_calls`` sums, where not 0 (e.g. the closed
    form's ``n_alpha_limit``, the ANN's ``n_ood`` of ``n_ood_checked``); "" where none fired."""
    sums = {name: float(np.nansum(values)) for name, values in record.diagnostics.items()
            if name.startswith("n_") and name != "n_unconverged" and not name.endswith("_all_calls")}
    return ";".join(f"{name}={value:g}" for name, value in sorted(sums.items()) if value)


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


def case_task(_shared: Any, case: Case) -> tuple[driver.Record | None, float, str | None, list[str]]:
    """``warp_hcell.core.execution`` task: (record, wall seconds, None, warnings), or (None, seconds, error line,
    warnings); the warnings the case raised are returned as one line each (the process that writes says them)."""
    start = time.perf_counter()
    with task_warnings() as caught:
        try:
            record, error = compute_case(case), None
        except CASE_ERRORS as exc:
            record, error = None, " ".join(str(exc).split()) or type(exc).__name__
    return record, time.perf_counter() - start, error, list(dict.fromkeys(caught))


