"""What a meso-ANN certificate must cover, and what it covers: the minimum certificate and the envelope.

- ``MINIMUM`` (a frozen ``MinimumCertificate``): the weakest certificate that counts as passed,
  for planar and spatial cells alike (pressures, axial strain, increment, target, planar
  orientations, spatial rule, rollouts, and the tests every certificate must hold). The
  defaults of ``homogenization.learning.certificate`` are this minimum.
- ``shortfalls(cert, dim)``: where a certificate is weaker than ``MINIMUM`` (one phrase each;
  empty: it meets the minimum). Read from the certificate's recorded ``settings``, ``tests``
  and ``rollout``, never from its ``passed`` flag.
- ``envelope_of(cert)``: what a certificate covers: ``pressures`` [lowest, highest] p0 of its
  tests [N/m in 2D, Pa in 3D], ``eps_max`` (largest axial strain of a shear stage counted
  from its start, either sense [-]), ``kinds`` (the test kinds, ``step_kind``), ``senses``,
  ``increment`` [-], ``mesostructure`` (name), ``cell_parameters`` (e.g. ``alpha0_deg``) and
  ``tests`` ([kind, sense, p0] of each test).
  Derived from the recorded ``settings`` and ``tests`` (a certificate written before the
  envelope was recorded has the same information).
- ``outside(envelope, programme, meso)``: where a run leaves the envelope, one phrase each.
- ``has_fine_grains(meso)``: whether a cell has grains driven along no axis, whose default surrogate is
  the hybrid (``homogenization.learning.settings.default_equilibrium``, ``policy.default_escalation``).
- ``equilibrium_settings(cert)``: (K, tolerance) of the surrogate a certificate measured: the
  network with K equilibrium corrections at that force ratio [-], or (0, None), the network alone;
  the ANN backend certifies runs of that very surrogate only.

Sign convention: compression and contraction positive; axial strain eps11 > 0 in compression.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization.element_test import programme as programmes
from homogenization.ann.records import Certificate
from warp_hcell.core.dimension import dimension

PRESSURE_RTOL = 1e-9
"""Relative tolerance of pressure and strain comparisons (round-off of recorded numbers) [-]."""


@dataclass(frozen=True)
class MinimumCertificate:
    """The weakest certificate that counts as passed (docs/certificate.md, "The minimum certificate")."""

    pressures: tuple[float, ...] = (2e5, 1e6)
    """Confining pressures p0 every certificate tests [N/m in 2D, Pa in 3D]."""
    eps_max: float = 0.10
    """Least axial strain of each shear stage [-]."""
    increment: float = 1e-4
    """Largest strain increment of the tests [-]."""
    target: float = 0.02
    """Largest target a passing certificate may set: dp, dq as fractions of the scale [-]."""
    n_orientations: int = 24
    """Least cell orientations of every test of a planar cell [-]."""
    spatial_rule: tuple[int, int] = (11, 4)
    """Least (Lebedev order, spins) of every test of a spatial cell."""
    rollout: bool = True
    """Whether the single-cell rollouts must have been run (``training.rollout``)."""
    planar_tests: tuple[tuple[str, str], ...] = (("constant-volume", "compression"), ("drained", "compression"),
                                                  ("drained", "extension"), ("constant-volume", "reversal"))
    """(kind, sense) of the tests every certificate of a planar cell holds (at every pressure, the
    reversal at one; constant-volume extension equals compression turned by 90 deg for
    the even orientation sets, ``certificate.tests_of``, so it is not required)."""
    spatial_tests: tuple[tuple[str, str], ...] = (("undrained", "compression"), ("undrained", "extension"),
                                                   ("drained", "compression"), ("drained", "extension"),
                                                   ("undrained", "reversal"))
    """(kind, sense) of the tests every certificate of a spatial cell holds."""

    def tests(self, dim: int) -> tuple[tuple[str, str], ...]:
        """The required (kind, sense) of the tests of cells of dimension ``dim`` (2 or 3; KeyError otherwise)."""
        return {2: self.planar_tests, 3: self.spatial_tests}[dim]


MINIMUM = MinimumCertificate()
"""The minimum certificate of the package (the defaults of ``homogenization.learning.certificate``)."""


def has_fine_grains(meso: Any) -> bool:
    """Whether ``meso`` (a ``Mesostructure``) has a grain driven along no axis: a fine grain whose
    position only its contacts' balance decides (the lateral spheres of the ten-sphere cell are
    driven across n and count not)."""
    return bool(np.any(~np.asarray(meso.driven, dtype=bool).any(axis=1)))


def _covers(value: float, least: float) -> bool:
    return value >= least * (1.0 - PRESSURE_RTOL)


def shortfalls(cert: Certificate, dim: int, minimum: MinimumCertificate = MINIMUM) -> list[str]:
    """Where certificate ``cert`` of cells of dimension ``dim`` is weaker than ``minimum``: one
    phrase each (e.g. "2 orientations (minimum 24)"); empty when it meets the minimum."""
    settings = cert.settings
    missing: list[str] = []
    pressures = sorted(float(p) for p in settings.get("pressures", ()))
    if not all(any(math.isclose(p, q, rel_tol=PRESSURE_RTOL) for p in pressures) for q in minimum.pressures):
        missing.append(f"pressures {', '.join(f'{p:g}' for p in pressures) or 'none'} "
                       f"(minimum: {', '.join(f'{p:g}' for p in minimum.pressures)})")
    eps_max = float(settings.get("eps_max", 0.0))
    if not _covers(eps_max, minimum.eps_max):
        missing.append(f"eps_max {eps_max:g} (minimum {minimum.eps_max:g})")
    increment = float(settings.get("increment", math.inf))
    if increment > minimum.increment * (1.0 + PRESSURE_RTOL):
        missing.append(f"increment {increment:g} (maximum {minimum.increment:g})")
    target = float(cert.target)
    if target > minimum.target * (1.0 + PRESSURE_RTOL):
        missing.append(f"target {100 * target:g} % (maximum {100 * minimum.target:g} %)")
    missing += _ORIENTATION_SHORTFALLS[dim](settings, minimum)
    if minimum.rollout and not cert.rollout:
        missing.append("no rollouts (the minimum runs them)")
    missing += _absent_tests(cert, dim, minimum, pressures)
    return missing


def _absent_tests(cert: Certificate, dim: int, minimum: MinimumCertificate, pressures: list[float]) -> list[str]:
    """The phrase naming the required tests ``cert`` lacks: each (kind, sense) of ``minimum.tests(dim)`` at every
    minimum pressure the certificate ran (``pressures``), a reversal at any one pressure (``certificate.tests_of``
    runs it at the first given); empty if none lacks."""
    ran = [q for q in minimum.pressures if any(math.isclose(p, q, rel_tol=PRESSURE_RTOL) for p in pressures)]
    absent = []
    for kind, sense in minimum.tests(dim):
        need = [] if sense == "reversal" else ran
        lacking = [q for q in need if not any((t.kind, t.sense) == (kind, sense)
                                              and math.isclose(float(t.p0), q, rel_tol=PRESSURE_RTOL) for t in cert.tests)]
        held = any((t.kind, t.sense) == (kind, sense) for t in cert.tests)
        if not held:
            absent.append(f"{kind} {sense}")
        elif lacking:
            absent.append(f"{kind} {sense} at p0 {', '.join(f'{q:g}' for q in lacking)}")
    return [f"no {', '.join(absent)} test"] if absent else []


def _planar_orientation_shortfalls(settings: Mapping[str, Any], minimum: MinimumCertificate) -> list[str]:
    n = int(settings.get("n_orientations", 0))
    return [f"{n} orientations (minimum {minimum.n_orientations})"] if n < minimum.n_orientations else []


def _spatial_orientation_shortfalls(settings: Mapping[str, Any], minimum: MinimumCertificate) -> list[str]:
    order, spins = (settings.get("spatial_rule") or (0, 0))
    if order < minimum.spatial_rule[0] or spins < minimum.spatial_rule[1]:
        return [f"spatial rule order {order} x {spins} spins (minimum {minimum.spatial_rule[0]} x "
                f"{minimum.spatial_rule[1]})"]
    return []


_ORIENTATION_SHORTFALLS = {2: _planar_orientation_shortfalls, 3: _spatial_orientation_shortfalls}
"""(recorded settings, minimum) -> where the orientations of a certificate of cells of each dimension fall
short (``shortfalls``)."""


def dimension_of(cert: Certificate) -> int:
    """Cell dimension of certificate ``cert``: 3 where its settings hold a ``spatial_rule``, else 2."""
    return 3 if "spatial_rule" in cert.settings else 2


def verdict(cert: Certificate) -> str:
    """"passed" (worst <= target and the minimum met), "failed" (worst > target, or a test the
    ANN could not follow) or "weak" (within the target, below ``MINIMUM``: not passed); read
    from the certificate's figures and settings, not from its ``passed`` flag."""
    worst, target = float(cert.worst), float(cert.target)
    if not worst <= target:
        return "failed"
    return "weak" if shortfalls(cert, dimension_of(cert)) else "passed"


def envelope_of(cert: Certificate) -> dict[str, Any]:
    """The envelope of certificate ``cert`` (module docstring): its ``envelope`` entry where it
    records one, else derived from its ``settings`` and ``tests``; ``tests`` ([kind, sense, p0] of every test)
    from its tests where the entry has none."""
    tests = cert.tests
    tested = sorted({(str(t.kind), str(t.sense), float(t.p0)) for t in tests})
    if cert.envelope is not None:
        return {"tests": [list(t) for t in tested], **cert.envelope}
    settings = cert.settings
    p0 = [float(t.p0) for t in tests] or [float(p) for p in settings.get("pressures", ())]
    return {
        "tests": [list(t) for t in tested],
        "pressures": [min(p0), max(p0)] if p0 else None,
        "eps_max": float(settings["eps_max"]) if "eps_max" in settings else None,
        "increment": float(settings["increment"]) if "increment" in settings else None,
        "kinds": sorted({str(t.kind) for t in tests}),
        "senses": sorted({str(t.sense) for t in tests}),
        "mesostructure": settings.get("mesostructure"),
        "cell_parameters": dict(cert.cell_parameters or settings.get("cell_parameters") or {}),
    }


def step_kind(step: programmes.Step, p0: float | None) -> str:
    """Kind of a shear step as the certificate names its tests: ``Dimension.isochoric_test``
    ("constant-volume", planar, or "undrained", spatial) where every lateral strain increment is
    ``Dimension.undrained_lateral`` of the axial one (to 1e-6: d_eps22 = -d_eps11 in the plane,
    ``programme.isochoric`` in space), "drained" (axial strain, the lateral stresses held at ``p0``,
    no coupling), else "other"."""
    rtol = 1e-9
    if all(c == "strain" for c in step.control):
        space = dimension(step.dim)
        d = step.target[0] / step.n_increments
        lateral = space.undrained_lateral(d)
        if all(math.isclose(t / step.n_increments, lateral, rel_tol=1e-6, abs_tol=1e-15) for t in step.target[1:]):
            return space.isochoric_test
        return "other"
    if (step.control[0] == "strain" and all(c == "stress" for c in step.control[1:]) and step.coupling is None
            and p0 is not None and all(math.isclose(t, p0, rel_tol=rtol) for t in step.target[1:])):
        return "drained"
    return "other"


def outside(envelope: Mapping[str, Any], programme: programmes.Programme, *, mesostructure: str | None = None,
            cell_parameters: Mapping[str, float] | None = None, unit: str = "N/m") -> list[str]:
    """Where ``programme`` (run on the cell named ``mesostructure`` with ``cell_parameters``)
    leaves ``envelope`` (``envelope_of``): one phrase each, empty inside.

    Checked: every isotropic stage's p0 (``stop_at_p``) within the certified pressures (a
    programme without one: not a certified test); the kind of every other step among the
    certified kinds (``step_kind``); each shear stage's kind and sense (compression, extension, or
    reversal where its axial strain turns) among the certified tests', at a p0 within theirs
    (``_untested``; where the envelope lists its ``tests``); the axial strain eps11 counted from the
    end of each isotropic stage within +-eps_max; every such step's axial strain increment at most
    the certified ``increment`` (the network's error grows with it: docs/ann.md); the cell's
    parameters where given (e.g. ``alpha0_deg``; names are not compared: a builder spec and a file
    name the same cell differently, and the backend's own ``check_start_cell`` bounds the learning
    state). ``unit``: stress unit of the phrases."""
    exits: list[str] = []
    low, high = envelope.get("pressures") or (None, None)
    p0 = None
    strain, largest = 0.0, 0.0
    kinds: list[str] = []
    coarsest = 0.0
    started = False
    segments: list[tuple[float | None, set[str], set[float]]] = []  # per isotropic stage: p0, kinds, axial signs
    for step in programme:
        if step.stop_at_p is not None:
            p0 = step.stop_at_p
            segments.append((p0, set(), set()))
            if low is not None and p0 < low * (1.0 - PRESSURE_RTOL):
                exits.append(f"p0 = {p0:g} {unit} below the lowest certified pressure {low:g} {unit}")
            elif high is not None and p0 > high * (1.0 + PRESSURE_RTOL):
                exits.append(f"p0 = {p0:g} {unit} above the highest certified pressure {high:g} {unit}")
            started, strain = True, 0.0
            continue
        if not started:
            exits.append(f"step {step.label!r} comes before any isotropic compression to p0 (every certified test "
                         f"starts with one)")
            started = True
        kind = step_kind(step, p0)
        if kind not in envelope.get("kinds", ()) and kind not in kinds:
            kinds.append(kind)
        if segments:
            segments[-1][1].add(kind)
            if step.control[0] == "strain" and step.target[0] != 0.0:
                segments[-1][2].add(math.copysign(1.0, step.target[0]))
        if step.control[0] == "strain":
            strain += step.target[0]
            largest = max(largest, abs(strain))
            coarsest = max(coarsest, abs(step.target[0]) / step.n_increments)
    if kinds:
        certified = ", ".join(envelope.get("kinds", ())) or "none"
        exits.append(f"test kind {', '.join(kinds)} not certified (certified: {certified})")
    eps_max = envelope.get("eps_max")
    if eps_max is not None and largest > eps_max * (1.0 + 1e-6):
        exits.append(f"axial strain {largest:g} beyond the certified {eps_max:g}")
    within = [(p, k, s) for p, k, s in segments  # a p0 outside the pressures is reported above
              if low is None or low * (1.0 - PRESSURE_RTOL) <= p <= high * (1.0 + PRESSURE_RTOL)]
    exits += _untested(envelope.get("tests"), within, unit)
    increment = envelope.get("increment")
    if increment is not None and coarsest > increment * (1.0 + 1e-6):
        exits.append(f"axial strain increment {coarsest:g} coarser than the certified {increment:g}")
    for key, value in (envelope.get("cell_parameters") or {}).items() if cell_parameters is not None else ():
        given = cell_parameters.get(key)
        if given is None or not math.isclose(float(given), float(value), rel_tol=1e-9):
            shown = "none" if given is None else f"{float(given):g}"
            exits.append(f"cell {mesostructure!r}: {key} = {shown} (certified: {float(value):g})")
    return exits


def _untested(tests: Sequence[Sequence[Any]] | None, segments: Sequence[tuple[float | None, set[str], set[float]]],
              unit: str) -> list[str]:
    """Where a shear stage (``segments``: its p0, step kinds and the signs of its axial strain steps) is of a
    (kind, sense) no certified test ran (``tests``: [kind, sense, p0]) or at a p0 outside those tests' range;
    sense: "reversal" where the axial strain turns, else "compression" or "extension". A planar constant-volume
    extension counts as the compression (the same test turned by 90 deg, ``MinimumCertificate.planar_tests``)."""
    if not tests:
        return []
    ranges: dict[tuple[str, str], list[float]] = {}
    for kind, sense, p0 in tests:
        ranges.setdefault((str(kind), str(sense)), []).append(float(p0))
    exits = []
    for p0, kinds, signs in segments:
        sense = "reversal" if len(signs) > 1 else "extension" if signs == {-1.0} else "compression"
        for kind in sorted(kinds - {"other"}):
            key = (kind, sense)
            if key not in ranges and key == ("constant-volume", "extension"):
                key = ("constant-volume", "compression")
            if key not in ranges:
                exits.append(f"a {kind} {sense} stage, which no certified test ran")
            elif p0 is not None and not (min(ranges[key]) * (1.0 - PRESSURE_RTOL) <= p0
                                         <= max(ranges[key]) * (1.0 + PRESSURE_RTOL)):
                lo, hi = min(ranges[key]), max(ranges[key])
                where = f"{lo:g} {unit}" if lo == hi else f"{lo:g} to {hi:g} {unit}"
                exits.append(f"a {kind} {sense} stage at p0 = {p0:g} {unit} (certified at {where})")
    return exits


def summary(exits: Sequence[str]) -> str:
    """One line of ``outside``'s phrases ('' inside the envelope)."""
    return "" if not exits else "outside its certificate's envelope: " + "; ".join(exits)

def equilibrium_settings(cert: Certificate) -> tuple[int, float | None]:
    """(K, tolerance) of the ANN runs certificate ``cert`` measured: (0, None) for the network alone
    (a certificate that records no equilibrium corrections)."""
    settings = cert.settings
    corrections = int(settings.get("equilibrium_corrections", 0))
    return (corrections, float(settings["equilibrium_tolerance"])) if corrections else (0, None)


def escalation_of(cert: Certificate) -> bool:
    """Whether the hybrid that certificate ``cert`` measured handed the cells with a released grain to the DEM
    (``homogenization.ann.escalation``; False where it records nothing: certified before that rule)."""
    return bool(cert.settings.get("dem_escalation", False))


def escalation_rule_of(cert: Certificate) -> str | None:
    """The rule by which the hybrid that certificate ``cert`` measured handed cells to the DEM
    (``homogenization.ann.escalation.RELEASE_RULE`` as it read then; None where it records none)."""
    return cert.settings.get("dem_escalation_rule")
