"""The certificate of a meso-ANN model: measure it against the DEM (the library of ``hmodel certify``).
The model against the DEM of its own mesostructure on
homogenised tests its database did not see (docs/certificate.md).

Tests (``tests_of``; constants below), by the cell's dimension. A planar cell: isotropic
compression to p0 (increments ``INCREMENT``), then constant-volume and drained (sigma22 = p0)
biaxial shear in compression (eps11 > 0) and extension (eps11 < 0; constant volume only for an
odd number of orientations, ``tests_of``) to ``EPS_MAX``, at every pressure of ``PRESSURES``,
and one reversal: constant-volume shear at ``PRESSURES[0]`` to +EPS_MAX / 2, then back to
-EPS_MAX / 2, on ``N_ORIENTATIONS`` cells. A spatial cell: the triaxial counterparts (axis 1
axial, ``programme.triaxial_shear``): undrained (isochoric) and drained (sigma22 = sigma33 = p0)
compression and extension at every pressure, and the undrained reversal, on the Lebedev rule
times spins ``SPATIAL_RULE`` over the cell's spin period (``Mesostructure.spin_period_deg``).
Each test runs through ``homogenization.element_test.driver.run`` with the ANN and with the DEM
(``homogenization.backends``) from the same mesostructure. Figures per test, over the shear
stages (the isotropic stages may differ by one increment, as p lands on p0): ``dp`` = max
abs(p_ann - p_dem) / scale, ``dq`` likewise, scale = max(p0, largest DEM p of the test). The
certificate passes when the worst of them is <= ``TARGET`` and its settings meet the minimum certificate
(``homogenization.ann.envelope.MINIMUM``; the constants below are that minimum).

Also reported, not part of ``worst``: the single-cell rollouts of ``training.rollout`` (held-out
constant-volume and drained legs, each error a fraction of that path's own largest moment: one
cell's grain engaging at another strain weighs there what 360 averaged cells do not), the
``coverage``: the fraction of the DEM cell states visited by the tests (every
``COVERAGE_EVERY``-th increment, all cells) within the out-of-distribution threshold of the
model's index (``training.ood``; None without one), and the DEM's own reproducibility: each
test's DEM run again with every increment started from rest (``homogenization.learning.from_rest``:
the map the database probes, without the velocity memory from which the DEM sets its next rate and
predicts its free grains), ``dem_spread`` = max over the shear stages of max(abs(p_dem - p_rest),
abs(q_dem - q_rest)) / scale. Where a sawtooth drop of the response (a fine grain leaving its
wedge) moves by an increment or two it exceeds the target: the reference does not resolve the
target there; the pass rule does not change.

The result (``certify``) is a ``homogenization.ann.records.Certificate`` (its fields say what
each entry holds), its verdict from ``homogenization.ann.envelope``. ``write_certificate`` stores it in
the model's JSON under ``"certificate"`` (the ANN backend then checks it), ``summary_lines`` are
what the commands print (one line per test, the verdict and the envelope) and ``exit_code`` the
verdict as their exit code: 0 passed, ``EXIT_FAILED`` (3) failed, ``EXIT_WEAK`` (4) within the
target but below the minimum. ``certify(dem_states=...)`` also hands back the DEM cell states met
along each test (the active-learning rounds of ``homogenization.learning.active`` probe those of the
failing tests). The command (its flags, its checks of bad input, --data, --write, --out) is
``homogenization.cli.certify`` (``hmodel certify``, ``python -m homogenization.certify``).

Sign convention: compression and contraction positive; stresses in N/m.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.learning.from_rest import FromRest
from homogenization.ann.records import Certificate, TestResult
from homogenization.ann.envelope import (dimension_of, envelope_of, equilibrium_settings, escalation_of, MINIMUM,
                                              shortfalls, verdict)
from homogenization.backends import make_cell_model
from homogenization.ann.escalation import RELEASE_RULE
from training.card import ModelCard, read_card, write_card
from training.ood import state_features
from training.rollout import rollout_report
from warp_hcell.core.files import atomic_write
from warp_hcell.core.parameters import DemSettings
from warp_hcell.core.provenance import file_sha256, git_revision
from warp_hcell.mesostructures.files import describe, description_sha256, from_description
from warp_hcell.mesostructures.mesostructure import Mesostructure

TARGET = MINIMUM.target
"""Largest dp or dq allowed, as a fraction of max(p0, largest DEM p) [-]."""
PRESSURES = MINIMUM.pressures
"""Confining pressures p0 of the tests [N/m]."""
EPS_MAX = MINIMUM.eps_max
"""Axial strain of each shear stage, counted from its start [-] (the reversal: +EPS_MAX / 2, then back by EPS_MAX)."""
INCREMENT = MINIMUM.increment
"""Strain increment of every stage [-] (isotropic: per component)."""
N_ORIENTATIONS = MINIMUM.n_orientations
"""Cell orientations of every homogenised test of a planar cell."""
SPATIAL_RULE = MINIMUM.spatial_rule
"""(Lebedev order, spins) of every homogenised test of a spatial cell: 25 axes x 4 spins = 100
cells (the test compares two backends cell by cell, so a coarse rule serves; docs/triaxial.md)."""
EXIT_FAILED = 3
"""Exit code of ``certify``, ``train`` and ``learn`` when the certificate failed (worst > target)."""
EXIT_WEAK = 4
"""Exit code of those commands when the certificate is within the target but below ``MINIMUM`` (not passed)."""
COVERAGE_EVERY = 50
"""Increments between two DEM states sampled for the coverage."""


def tests_of(pressures: Sequence[float] = PRESSURES, eps_max: float = EPS_MAX,
             increment: float = INCREMENT, n_orientations: int = N_ORIENTATIONS, dim: int = 2
             ) -> list[tuple[dict[str, Any], programmes.Programme]]:
    """(description, programme) of every test of a cell of dimension ``dim``: kind, sense, p0
    [N/m in 2D, Pa in 3D] and name.

    Planar: constant-volume extension is constant-volume compression turned by 90 deg; an even
    number of orientations evenly spaced over 180 deg (isotropic fabric) is its own image under
    that turn, so the two give the same curves to round-off (the shipped model's figures agree
    to 3e-7 of themselves) and extension is run only for an odd ``n_orientations``. Drained
    extension differs (sigma22 is held) and is always run. Spatial (``dim`` 3): axisymmetric
    extension is no turn of compression, so undrained and drained tests run in both senses.
    """
    return _TESTS_OF[dim](pressures, eps_max, increment, n_orientations)


def _planar_tests(pressures: Sequence[float], eps_max: float, increment: float, n_orientations: int
                  ) -> list[tuple[dict[str, Any], programmes.Programme]]:
    """The biaxial tests of a planar cell (``tests_of``)."""
    tests = []
    n = programmes.n_increments_for(eps_max, increment)
    for p0 in pressures:
        for kind in ("constant-volume", "drained"):
            senses = (("compression", 1.0), ("extension", -1.0))
            if kind == "constant-volume" and n_orientations % 2 == 0:
                senses = senses[:1]
            for sense, sign in senses:
                shear = (programmes.drained_biaxial(p0, sign * eps_max, n) if kind == "drained"
                         else programmes.constant_volume_biaxial(sign * eps_max, n))
                tests.append(({"name": f"{kind} {sense} p0={p0:g}", "kind": kind, "sense": sense, "p0": p0},
                              (programmes.isotropic(p0, increment=increment), shear)))
    p0, half = pressures[0], programmes.n_increments_for(eps_max / 2, increment)
    tests.append(({"name": f"constant-volume reversal p0={p0:g}", "kind": "constant-volume", "sense": "reversal", "p0": p0},
                  (programmes.isotropic(p0, increment=increment),
                   programmes.constant_volume_biaxial(eps_max / 2, half, label="shear"),
                   programmes.constant_volume_biaxial(-eps_max, 2 * half, label="reverse"))))
    return tests


def _spatial_tests(pressures: Sequence[float], eps_max: float, increment: float, n_orientations: int
                   ) -> list[tuple[dict[str, Any], programmes.Programme]]:
    """The triaxial tests of a spatial cell (``tests_of``; ``n_orientations`` is a planar setting, unused)."""
    tests = []
    n = programmes.n_increments_for(eps_max, increment)
    for p0 in pressures:
        iso = programmes.isotropic(p0, increment=increment, dim=3)
        shears = {("undrained", "compression"): programmes.isochoric(eps_max, n),
                  ("undrained", "extension"): programmes.isochoric(-eps_max, n),
                  ("drained", "compression"): programmes.triaxial_shear("drained", p0, eps_max, n)[0],
                  ("drained", "extension"): programmes.triaxial_shear("extension", p0, eps_max, n)[0]}
        for (kind, sense), shear in shears.items():
            tests.append(({"name": f"{kind} {sense} p0={p0:g}", "kind": kind, "sense": sense, "p0": p0}, (iso, shear)))
    p0, half = pressures[0], programmes.n_increments_for(eps_max / 2, increment)
    tests.append(({"name": f"undrained reversal p0={p0:g}", "kind": "undrained", "sense": "reversal", "p0": p0},
                  (programmes.isotropic(p0, increment=increment, dim=3),
                   programmes.isochoric(eps_max / 2, half, label="shear"),
                   programmes.isochoric(-eps_max, 2 * half, label="reverse"))))
    return tests


_TESTS_OF = {2: _planar_tests, 3: _spatial_tests}
"""The tests of a certificate of cells of each dimension (``tests_of``)."""
_ORIENTATION_SETTINGS = {
    2: lambda n_orientations, spatial_rule: {"n_orientations": int(n_orientations)},
    3: lambda n_orientations, spatial_rule: {"spatial_rule": [int(k) for k in spatial_rule], "staggered_spins": True},
}
"""(n_orientations, spatial_rule) -> the orientation settings a certificate of cells of each dimension records."""
_ORIENTATION_ARGUMENTS = {
    2: lambda settings: {"n_orientations": settings["n_orientations"]},
    3: lambda settings: {"lebedev_order": settings["spatial_rule"][0], "n_spins": settings["spatial_rule"][1],
                         "staggered_spins": settings["staggered_spins"]},
}
"""Recorded settings -> the orientation arguments of ``driver.run`` for cells of each dimension."""


def requested_settings(dim: int, *, pressures: Sequence[float] = PRESSURES, eps_max: float = EPS_MAX,
                       increment: float = INCREMENT, n_orientations: int = N_ORIENTATIONS,
                       spatial_rule: Sequence[int] = SPATIAL_RULE, equilibrium_corrections: int = 0,
                       equilibrium_tolerance: float | None = None, dem_escalation: bool = False,
                       release_rule: str = RELEASE_RULE) -> dict[str, Any]:
    """The ``settings`` a certificate of cells of dimension ``dim`` records for these options
    (planar: ``n_orientations``; spatial: ``spatial_rule`` as [order, spins], with the spins
    staggered from axis to axis, ``staggered_spins``: ``homogenization.material.orientation``;
    with ``equilibrium_corrections`` K > 0 also K and ``equilibrium_tolerance``, the resolved force
    ratio [-] of the hybrid its tests ran: ``envelope.equilibrium_settings``, and ``dem_escalation``, whether
    it handed the cells with a released grain to the DEM: ``envelope.escalation_of``, with the rule it did it
    by, ``dem_escalation_rule``: ``release_rule``, one of ``homogenization.ann.escalation.RELEASE_RULES``)."""
    settings = {"pressures": [float(p) for p in pressures], "eps_max": float(eps_max), "increment": float(increment)}
    hybrid = ({"equilibrium_corrections": int(equilibrium_corrections), "equilibrium_tolerance": float(equilibrium_tolerance),
               "dem_escalation": bool(dem_escalation), **({"dem_escalation_rule": release_rule} if dem_escalation else {})}
              if equilibrium_corrections else {})
    return {**settings, **_ORIENTATION_SETTINGS[dim](n_orientations, spatial_rule), **hybrid}


def run_test(model: Any, programme: programmes.Programme, meso: Mesostructure, settings: dict[str, Any]) -> driver.Record:
    """``programme`` on cells of ``model`` from ``meso``, oriented as ``settings`` say
    (``requested_settings``: planar ``n_orientations``, spatial ``spatial_rule``)."""
    return driver.run(model, programme, mesostructure=meso, progress=False,
                      **_ORIENTATION_ARGUMENTS[meso.dim](settings))


class _Counter:
    """A cell model that passes every call to ``model`` and counts the increments of a run: the
    distinct start states of its ``step`` calls (the trial calls of a stress-controlled increment
    start from one state: counted once). ``increment`` is the index of the latest start state
    within the current test (``test``, set by the caller; 0 the first state of the test)."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.name = model.name
        self.test = 0
        self.increment = -1
        self._last: object = None
        self._counted_test = 0
        self.corrections = {"steps": 0, "n_corrected": 0, "n_corrections": 0, "n_shortened": 0, "n_shifted": 0,
                            "n_unconverged": 0, "n_escalated": 0,
                            "force_ratio_network_max": 0.0, "force_ratio_max": 0.0}

    def __getattr__(self, name: str) -> Any:
        return getattr(self.model, name)

    def _count(self, state: Any) -> bool:
        """Count ``state``; whether it is a new start state."""
        if state is self._last:
            return False
        if self.test != self._counted_test:
            self._counted_test, self.increment = self.test, -1
        self._last = state
        self.increment += 1
        return True

    def step(self, state: Any, d_eps: np.ndarray, *, with_tangent: bool = False):
        self._count(state)
        new, response = self.model.step(state, d_eps, with_tangent=with_tangent)
        self._tally(response.diagnostics)
        return new, response

    def _tally(self, diagnostics: dict[str, float]) -> None:
        """Add one step's equilibrium-correction counts (``AnnCell``; none without corrections) to
        ``corrections``: calls (``steps``, trial calls included), cells corrected, Newton steps, cells
        left above the tolerance, cells with a released grain (``n_released``, ``n_released_pushed``, ``n_relaxed``
        and its substeps, where the hybrid reports them) and handed to the DEM (summed), and the largest force ratios."""
        if "n_corrected" not in diagnostics:
            return
        tally = self.corrections
        tally["steps"] += 1
        for key in ("n_corrected", "n_corrections", "n_shortened", "n_shifted", "n_unconverged", "n_escalated"):
            tally[key] += int(diagnostics.get(key, 0))
        for key in ("n_released", "n_released_pushed", "n_relaxed", "n_relaxed_substeps", "n_relaxed_unconverged"):
            # hybrids with a released-grain rule only; n_relaxed...: escalation.RELEASE_RULE_DRAG only
            if key in diagnostics:
                tally[key] = tally.get(key, 0) + int(diagnostics[key])
        for key in ("force_ratio_network_max", "force_ratio_max"):
            tally[key] = max(tally[key], float(diagnostics[key]))


class _Sampler(_Counter):
    """A ``_Counter`` that also keeps, every ``every``-th distinct start state (counted over all
    tests), the DEM state arrays (``cell_size``, ``position``, ``shear_force``) of its cells and
    the ``increment`` of that state within its test; every ``COVERAGE_EVERY``-th one is also
    kept for the coverage."""

    def __init__(self, model: Any, every: int) -> None:
        super().__init__(model)
        self.every = every
        self.coverage: list[dict[str, np.ndarray]] = []
        self.states: dict[int, list[dict[str, np.ndarray]]] = {}
        self._seen = 0

    def step(self, state: Any, d_eps: np.ndarray, *, with_tangent: bool = False):
        if self._count(state):
            keep, cover = self._seen % self.every == 0, self._seen % COVERAGE_EVERY == 0
            if keep or cover:
                arrays = self.model.state_to_arrays(state)
                kept = {name: np.array(arrays[name]) for name in ("cell_size", "position", "shear_force")}
                if keep:
                    n = kept["cell_size"].shape[0]
                    self.states.setdefault(self.test, []).append({**kept, "increment": np.full(n, self.increment)})
                if cover:
                    self.coverage.append(kept)
            self._seen += 1
        return self.model.step(state, d_eps, with_tangent=with_tangent)


def departure(a: driver.Record, d: driver.Record, scale: float, target: float) -> int | None:
    """The increment [-] (counted from the start of the test, as ``_Counter.increment``) whose
    result first puts the ANN's p or q more than ``target`` x ``scale`` off the DEM's, over the
    shear stages; None where it never does."""
    ra, rd = _shear_rows(a), _shear_rows(d)
    off = np.nan_to_num(np.maximum(np.abs(a.p[ra] - d.p[rd]), np.abs(a.q[ra] - d.q[rd])), nan=math.inf) > target * scale
    return int(np.flatnonzero(rd)[np.argmax(off)]) if off.any() else None


def _jumps(record: driver.Record) -> int:
    """Increments of ``record`` whose stress control accepted the trial nearest its target across a jump of
    the response (``stress_control_jump``, ``homogenization.element_test.driver``)."""
    return int(np.nansum(record.diagnostics.get("stress_control_jump", np.zeros(0))))


def _shear_rows(record: driver.Record) -> np.ndarray:
    return record.stage != record.programme[0].label


def _paired_shear_rows(x: driver.Record, y: driver.Record, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The shear-stage rows of two runs ``x`` and ``y`` of test ``name``, as many in both."""
    rx, ry = _shear_rows(x), _shear_rows(y)
    if rx.sum() != ry.sum():
        raise ValueError(f"test {name!r}: two runs ({x.backend}, {y.backend}) recorded different shear lengths")
    return rx, ry


def _compare(a: driver.Record, d: driver.Record, name: str, scale: float, target: float) -> dict[str, Any]:
    """The figures of test ``name`` (module docstring) from the ANN's record ``a`` and the DEM's ``d``:
    ``dp``, ``dq`` [-], and where they arise ``departure`` and ``stress_control_jumps``."""
    ra, rd = _paired_shear_rows(a, d, name)
    dp, dq = (float(np.nan_to_num(np.abs(x[ra] - y[rd]), nan=math.inf).max()) / scale for x, y in ((a.p, d.p), (a.q, d.q)))
    left = departure(a, d, scale, target)
    jumps = {"ann": _jumps(a), "dem": _jumps(d)}
    return {"dp": dp, "dq": dq, **({} if left is None else {"departure": left}),
            **({"stress_control_jumps": jumps} if any(jumps.values()) else {})}


def _dem_spread(rest: FromRest, test: tuple[dict[str, Any], programmes.Programme], meso: Mesostructure,
                settings: dict[str, Any], d: driver.Record, scale: float) -> dict[str, Any]:
    """``dem_spread`` of ``test`` (description, programme): its programme run by the DEM ``rest`` started
    from rest in every increment, max over the shear stages of max(abs(p_dem - p_rest), abs(q_dem -
    q_rest)) / ``scale`` [-] against the DEM's record ``d``; inf and ``dem_spread_error`` where it could
    not follow the programme."""
    info, programme = test
    try:
        r = run_test(rest, programme, meso, settings)
    except driver.ControlError as exc:
        return {"dem_spread": math.inf, "dem_spread_error": " ".join(str(exc).split())}
    rr, rd = _paired_shear_rows(r, d, info["name"])
    off = np.maximum(np.abs(r.p[rr] - d.p[rd]), np.abs(r.q[rr] - d.q[rd]))
    return {"dem_spread": float(np.nan_to_num(off, nan=math.inf).max()) / scale}


def _widest_spread(results: list[dict[str, Any]], target: float) -> dict[str, Any]:
    """The certificate's ``dem_spread``: the largest of its tests' [-] (``max``), that test's name
    (``test``) and the names of the tests whose spread exceeds ``target`` (``above_target``)."""
    widest = max(results, key=lambda t: t["dem_spread"])
    return {"max": widest["dem_spread"], "test": widest["name"],
            "above_target": [t["name"] for t in results if t["dem_spread"] > target]}


def _scale(info: dict[str, Any], d: driver.Record) -> float:
    """The scale of a test's figures (module docstring): max(p0, the largest p of the DEM's record ``d``)."""
    return max(float(info["p0"]), float(np.max(d.p)))


@dataclasses.dataclass(frozen=True)
class _DemReference:
    """The DEM's side of a certificate's tests (it does not depend on the model): per test its record and
    its ``dem_spread`` entry ({} without the reproducibility run), and ``_Sampler``'s states and coverage."""

    records: list[driver.Record]
    spreads: list[dict[str, Any]]
    states: dict[int, list[dict[str, np.ndarray]]]
    coverage: list[dict[str, np.ndarray]]


_LAST_REFERENCE: dict[str, _DemReference] = {}
"""The latest ``_DemReference`` by its key (one entry): the rounds of ``hmodel learn`` certify every candidate on
the same tests in one process, and the DEM then runs them once."""


def _dem_reference(meso: Mesostructure, law: Any, settings: DemSettings, tests: list, requested: dict[str, Any],
                   state_every: int, reproducibility: bool, threads: int) -> _DemReference:
    """The DEM runs of ``tests`` (``tests_of``) on ``meso`` with the contact ``law`` and ``settings``, states kept
    every ``state_every`` increments, the reproducibility runs where asked; the latest call's result again where
    nothing of these differs (the DEM's results do not depend on ``threads``)."""
    key = json.dumps([description_sha256(describe(meso)), repr(law), dataclasses.asdict(settings),
                      [info for info, _ in tests], requested, state_every, reproducibility], default=str,
                     sort_keys=True)
    if key in _LAST_REFERENCE:
        return _LAST_REFERENCE[key]
    dem = make_cell_model("dem", contact_law=law, radius=float(meso.radius.mean()), settings=settings, threads=threads)
    sampler = _Sampler(dem, state_every)
    rest = FromRest(dem) if reproducibility else None
    records, spreads = [], []
    for k, test in enumerate(tests):
        sampler.test = k
        d = run_test(sampler, test[1], meso, requested)
        records.append(d)
        spreads.append({} if rest is None else _dem_spread(rest, test, meso, requested, d, _scale(test[0], d)))
    _LAST_REFERENCE.clear()
    _LAST_REFERENCE[key] = _DemReference(records, spreads, sampler.states, sampler.coverage)
    return _LAST_REFERENCE[key]


def certify(model_path: Path, *, mesostructure: Mesostructure | None = None, pressures: Sequence[float] = PRESSURES,
            eps_max: float = EPS_MAX, increment: float = INCREMENT, n_orientations: int = N_ORIENTATIONS,
            spatial_rule: Sequence[int] = SPATIAL_RULE, target: float = TARGET, rollout: bool = True, threads: int = 1,
            dem_states: dict[str, dict[str, np.ndarray]] | None = None, state_every: int = COVERAGE_EVERY,
            equilibrium_corrections: int = 0, equilibrium_tolerance: float | None = None,
            reproducibility: bool = True, card: ModelCard | None = None, release_rule: str = RELEASE_RULE) -> Certificate:
    """The certificate of model ``model_path`` (module docstring); ``mesostructure`` None: the
    model's own; ``card``: the model's JSON already read (None: read here); ``reproducibility``
    False: no ``dem_spread`` (the DEM is not run a second time, from rest); ``release_rule``: the hybrid's
    (``escalation.RELEASE_RULES``), recorded.

    ``dem_states``, when given, receives per test name the DEM cell states every ``state_every``
    increments (``DemCell.state_to_arrays``: ``cell_size``, ``position``, ``shear_force``, local
    frame) with ``cell`` (an id per test and orientation) and ``increment`` (n,) int64: what the
    rounds probe.

    ``equilibrium_corrections`` K > 0 (spatial cells): the tests run the hybrid (``AnnCell``) at
    ``equilibrium_tolerance`` (None: the DEM's ``force_tolerance``); the certificate records K,
    the tolerance and how often the corrections fired, and covers runs with that K and tolerance only.

    Raises:
        ValueError (CheckpointError, one line): unusable model, or a mesostructure it does not take.
        homogenization.element_test.driver.ControlError: a stress-controlled increment of the
            DEM did not converge (the ANN's: that test fails with dp = dq = inf).
    """
    start = time.perf_counter()
    model_path = Path(model_path)
    card = read_card(model_path) if card is None else card
    law = card.law
    hybrid = ({"equilibrium_corrections": int(equilibrium_corrections), "equilibrium_tolerance": equilibrium_tolerance,
               "release_rule": release_rule}
              if equilibrium_corrections else {"equilibrium_corrections": 0})  # never the model's earlier certificate's
    ann = make_cell_model("ann", contact_law=law, model=model_path, threads=threads, card=card, **hybrid)
    meso = mesostructure if mesostructure is not None else from_description(card.mesostructure)
    ann.check_trained_on(meso)
    settings = DemSettings(contact_tolerance=float(card.contact_tolerance))
    free = ann.net.schema.free_dofs.cpu().numpy()
    requested = requested_settings(meso.dim, pressures=pressures, eps_max=eps_max, increment=increment,
                                   n_orientations=n_orientations, spatial_rule=spatial_rule,
                                   equilibrium_corrections=equilibrium_corrections,
                                   equilibrium_tolerance=ann.force_tolerance if equilibrium_corrections else None,
                                   dem_escalation=ann.escalation is not None, release_rule=release_rule)
    tests = tests_of(pressures, eps_max, increment, n_orientations, meso.dim)
    reference = _dem_reference(meso, law, settings, tests, requested, int(state_every), reproducibility, threads)
    results = []
    n_cells = reference.records[0].weights.size
    counter = _Counter(ann)
    for k, (test, d, spread) in enumerate(zip(tests, reference.records, reference.spreads)):
        info, programme = test
        counter.test = k
        scale = _scale(info, d)
        length = {"n_increments": int(d.p.size)}
        try:
            a = run_test(counter, programme, meso, requested)
        except driver.ControlError as exc:  # the ANN cannot follow the programme: the test fails
            results.append({**info, "dp": math.inf, "dq": math.inf, "scale": scale, "error": " ".join(str(exc).split()),
                            "departure": max(counter.increment, 0), **length, **spread})
            continue
        results.append({**info, **_compare(a, d, info["name"], scale, target), "scale": scale, **length, **spread})
    rows = tuple(TestResult.from_dict(t) for t in results)
    worst = max(rows, key=lambda t: t.figure)
    if dem_states is not None:
        for k, parts in reference.states.items():
            merged = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}
            cells = np.concatenate([np.arange(part["cell_size"].shape[0]) for part in parts])
            dem_states[results[k]["name"]] = {**merged, "cell": k * n_cells + cells}
    coverage = None
    if ann.ood is not None and reference.coverage:
        size, position, shear = (np.concatenate([part[name] for part in reference.coverage])
                                 for name in ("cell_size", "position", "shear_force"))
        inside = ~ann.ood.outside(state_features(ann.net, size, position[:, free[:, 0], free[:, 1]], shear))
        coverage = {"fraction_within": float(inside.mean()), "n_states": int(inside.size),
                    "threshold": ann.ood.threshold, "every_increments": COVERAGE_EVERY}
    report = (rollout_report(ann.net, meso, law, settings, increments=(increment,)) if rollout else None)
    cert = Certificate(
        target=target, worst=worst.figure, worst_test=worst.name,
        metric="max over the shear stages of abs(p_ann - p_dem) and abs(q_ann - q_dem) / max(p0, largest DEM p)",
        tests=rows, rollout=report, coverage=coverage,
        dem_spread=_widest_spread(results, target) if reproducibility else None,
        settings={**requested, "mesostructure": meso.name, "n_cells": n_cells},
        cell_parameters={k: float(v) for k, v in meso.parameters.items()},
        model_sha256=file_sha256(model_path), revision=git_revision(), seconds=time.perf_counter() - start,
        equilibrium=counter.corrections if equilibrium_corrections else None,
        within_target=bool(worst.figure <= target), below_minimum=[], verdict="", passed=False)
    cert = dataclasses.replace(cert, below_minimum=shortfalls(cert, meso.dim))
    result = verdict(cert)
    return dataclasses.replace(cert, verdict=result, passed=result == "passed", envelope=envelope_of(cert))


def write_certificate(model_path: Path, certificate: Certificate, card: ModelCard | None = None) -> Path:
    """Store ``certificate`` in the model's JSON under ``"certificate"`` (atomically; ``card``: that JSON
    already read, None: read here); returns the JSON path."""
    card = read_card(model_path) if card is None else card
    return write_card(model_path, dataclasses.replace(card, certificate=certificate.to_dict()))


def plot_worst_test(model_path: Path, cert: Certificate, out: Path, *, threads: int = 1,
                    card: ModelCard | None = None) -> Path:
    """Figure ``out`` (PNG, written atomically) of p and q [N/m] against eps11 [-] of the ANN and the
    DEM on the certificate's worst test (``cert.worst_test``, rerun with ``cert.settings``, the
    equilibrium corrections included; ``card``: the model's JSON already read, None: read here)."""
    from matplotlib.figure import Figure  # noqa: PLC0415 (matplotlib only where a figure is drawn)

    from homogenization.output.figure_style import apply_style, figure_legend, PNG_DPI  # noqa: PLC0415

    settings = cert.settings
    card = read_card(model_path) if card is None else card
    law = card.law
    meso = from_description(card.mesostructure)
    info, programme = next((i, prog) for i, prog in tests_of(settings["pressures"], settings["eps_max"],
                                                             settings["increment"], settings.get("n_orientations", 0),
                                                             meso.dim) if i["name"] == cert.worst_test)
    models = {"DEM": make_cell_model("dem", contact_law=law, radius=float(meso.radius.mean()),
                                     settings=DemSettings(contact_tolerance=float(card.contact_tolerance)),
                                     threads=threads),
              "ANN": make_cell_model("ann", contact_law=law, model=model_path, threads=threads, card=card,
                                     **_hybrid_of(cert))}
    fig = Figure(figsize=(8.0, 3.6), layout="constrained")
    axes = fig.subplots(1, 2)
    handles = []
    for (label, model), style in zip(models.items(), ({"color": "k"}, {"color": "C3", "linestyle": "--"})):
        try:
            record = run_test(model, programme, meso, settings)
        except driver.ControlError:  # the ANN cannot follow the programme: the DEM alone is drawn
            continue
        rows = _shear_rows(record)
        for ax, values in zip(axes, (record.p, record.q)):
            (line,) = ax.plot(record.eps11[rows], values[rows], label=label, **style)
        handles.append(line)
    for ax, name in zip(axes, ("p [N/m]", "q [N/m]")):
        ax.set(xlabel="eps11 [-]", ylabel=name)
    missing = "" if len(handles) == len(models) else " (the ANN could not follow the programme)"
    fig.suptitle(f"{info['name']}: worst {100 * cert.worst:.3g} % of the scale{missing}")
    figure_legend(fig, handles)
    with atomic_write(Path(out)) as tmp:
        apply_style(fig).savefig(tmp, dpi=PNG_DPI, format="png")
    return Path(out)


def _hybrid_of(cert: Certificate) -> dict[str, Any]:
    """The ANN backend's keywords of the surrogate certificate ``cert`` measured (K = 0: the network alone)."""
    corrections, tolerance = equilibrium_settings(cert)
    return ({"equilibrium_corrections": corrections, "equilibrium_tolerance": tolerance,
             "dem_escalation": escalation_of(cert)} if corrections else {"equilibrium_corrections": 0})


def summary_lines(cert: Certificate) -> list[str]:
    """One line per test, then the verdict."""
    lines = [f"{t.name:<40} dp {100 * t.dp:.3f} %  dq {100 * t.dq:.3f} %"
             + ("" if t.dem_spread is None else f"  DEM from rest off the DEM by {100 * t.dem_spread:.3f} %"
                + (" (above the target)" if t.dem_spread > cert.target else ""))
             + ("" if t.stress_control_jumps is None else
                f"  (accepted across a jump: ANN {t.stress_control_jumps['ann']}, DEM {t.stress_control_jumps['dem']})")
             for t in cert.tests]
    spread = cert.dem_spread
    if spread and spread["above_target"]:
        lines.append(f"the DEM's own reproducibility: started from rest in every increment it moves "
                     f"{len(spread['above_target'])} test(s) by up to {100 * spread['max']:.3f} % ({spread['test']}), "
                     f"above the target {100 * cert.target:.3g} %: "
                     "the target is finer than the reference resolves there")
    if cert.rollout is not None:
        inc = next(v for k, v in cert.rollout.items() if k.startswith("increment_"))
        lines.append(f"rollout (single cells, reported only): max {inc['max']:.4f}, median {inc['median']:.4f}")
    if cert.coverage is not None:
        lines.append(f"coverage: {100 * cert.coverage['fraction_within']:.2f} % of {cert.coverage['n_states']} "
                     f"DEM states within the out-of-distribution threshold")
    if cert.equilibrium is not None:
        k, tolerance = equilibrium_settings(cert)
        tally = cert.equilibrium
        lines.append(f"hybrid: the network with {k} equilibrium corrections at tolerance {tolerance:g}: "
                     f"{tally['n_corrected']} cell steps corrected ({tally['n_corrections']} Newton steps"
                     + (f", {tally['n_shortened']} shortened by the line search, {tally['n_shifted']} shifted"
                        if "n_shortened" in tally else "")
                     + ") over "
                     f"{tally['steps']} ANN calls, {tally['n_unconverged']} left above the tolerance, "
                     + (f"{tally.get('n_released', 0)} with a released grain taken again at rest "
                        f"({tally.get('n_released_pushed', 0)} pushed), {tally.get('n_escalated', 0)} handed to the DEM, "
                        if escalation_of(cert) else "")
                     + (f"{tally['n_relaxed']} relaxed as the DEM from rest ({tally.get('n_relaxed_substeps', 0)} substeps, "
                        f"{tally.get('n_relaxed_unconverged', 0)} at the cap), " if "n_relaxed" in tally else "")
                     + f"largest force ratio {tally['force_ratio_network_max']:.3g} before, {tally['force_ratio_max']:.3g} after")
    result = verdict(cert)
    figures = (f"worst {100 * cert.worst:.3f} % ({cert.worst_test}), target {100 * cert.target:.3g} %, "
               f"{cert.seconds:.1f} s")
    if result == "weak":
        lines.append(f"NOT PASSED (weak): {figures}, but the certificate is below the minimum: "
                     f"{'; '.join(shortfalls(cert, dimension_of(cert)))}")
    else:
        lines.append(f"{result.upper()}: {figures}")
    envelope = envelope_of(cert)
    if envelope["pressures"] is not None:
        lines.append(f"envelope: p0 {envelope['pressures'][0]:g} to {envelope['pressures'][1]:g}, axial strain within "
                     f"+-{envelope['eps_max']:g}, {', '.join(envelope['kinds'])} tests, cell {envelope['mesostructure']!r}")
    return lines


def exit_code(cert: Certificate) -> int:
    """Exit code of a command whose result is certificate ``cert``: 0 passed, ``EXIT_FAILED`` (3)
    failed, ``EXIT_WEAK`` (4) within the target but below the minimum certificate."""
    return {"passed": 0, "failed": EXIT_FAILED, "weak": EXIT_WEAK}[verdict(cert)]


if __name__ == "__main__":  # the command is in the command layer; an old command line gets one line, not silence
    print("python -m homogenization.learning.certificate: this is the library; the command is hmodel certify "
          "(python -m homogenization.certify)", file=sys.stderr)
    raise SystemExit(2)
