"""Loading programmes as data: mixed strain/stress control per component (spec section 9).

A ``Programme`` is a tuple of ``Step``s run one after the other by ``driver.run``. Each step
controls the normal components, in the order (11, 22) of a planar programme or (11, 22, 33)
of a spatial (triaxial) one, each by ``"strain"`` or ``"stress"``; macro shear strain
increments are always zero. All steps of a programme have one dimension.

- A strain-controlled component changes by ``target`` [-] over the step, in
  ``n_increments`` equal increments (the target counts from the start of the step).
- A stress-controlled component ends the step at sigma = ``target`` [N/m in 2D, Pa in 3D];
  the driver ramps it linearly from its value at the start of the step and solves the
  strain that gives it.
- ``coupling`` (optional, component 11 strain-controlled): a stress-controlled component i
  also follows the axial stress, sigma_i = ramp_i + coupling_i (sigma11 - sigma11 at the start
  of the step). Constant p in a triaxial test is coupling (0, -1/2, -1/2); a true triaxial test
  at constant b = (sigma2 - sigma3) / (sigma1 - sigma3) from an isotropic state is (0, b, 0)
  with sigma33 held.
- ``stop_at_p`` (only with strain control on every component): the step ends as soon as the
  mean stress p (tr(sigma) / dim) reaches ``stop_at_p``; the increment that would cross it is
  shortened (its strain increment scaled by a factor in (0, 1] solved by the driver) so that p
  lands on ``stop_at_p`` within the stress tolerance. Reaching the last increment first is an
  error. This is how the isotropic stage reaches p0 exactly while staying strain-driven.

Sign convention: compression and contraction positive (strains [-], stresses [N/m] in 2D,
[Pa] in 3D). ``to_dict``/``from_dict`` round-trip a programme through JSON-compatible data
(stored in the HDF5 attributes of a run); ``read_programme`` reads the same data from a JSON
or TOML file (``hmodel biaxial --programme FILE``, ``hmodel triaxial --programme FILE``;
format and examples in docs/programmes.md, example files in homogenization/data/programmes/).
"""

from __future__ import annotations

import difflib
import json
import math
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

from warp_hcell.core.dimension import dimension as dimension_of
from warp_hcell.core.parameters import LoadingDefaults

CONTROLS = ("strain", "stress")
"""Allowed control kinds of a component."""
COMPONENTS = dimension_of(2).normal_components
"""Controlled components of a planar step, in the order of ``Step.control`` and ``Step.target``."""
COMPONENTS_3D = dimension_of(3).normal_components
"""Controlled components of a spatial (triaxial) step; axis 1 is the axial direction."""
ISO_MAX_STRAIN = 0.1
"""Largest strain per component the isotropic stage may apply before giving up [-]."""
MAX_INCREMENTS = 10_000_000
"""Most increments of one step [-]: a run's record holds every increment (a smaller increment for its strain is
refused, not left to exhaust the memory)."""


@dataclass(frozen=True)
class Step:
    """One stage of a loading programme; validated on construction (one-line ValueError)."""

    control: tuple[str, ...]
    """Control of components (11, 22) or (11, 22, 33): each "strain" or "stress"."""
    target: tuple[float, ...]
    """Per component: strain change over the step [-] (strain control) or the stress at the
    end of the step [N/m in 2D, Pa in 3D] (stress control); compression positive."""
    n_increments: int
    """Number of increments of the step (an upper bound when ``stop_at_p`` is set)."""
    label: str
    """Stage label written to outputs (e.g. "iso", "shear")."""
    stop_at_p: float | None = None
    """End the step once p reaches this mean stress (strain control only)."""
    coupling: tuple[float, ...] | None = None
    """d sigma_i / d sigma11 imposed on stress-controlled components i (module docstring); None: none."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "control", tuple(self.control))
        object.__setattr__(self, "target", tuple(float(v) for v in self.target))
        count = "three" if len(self.control) == 3 else "two"  # a planar step unless three are given
        if len(self.control) not in (2, 3) or any(c not in CONTROLS for c in self.control):
            raise ValueError(f"step {self.label!r}: control must be {count} of {CONTROLS}, got {self.control}")
        if len(self.target) != len(self.control) or not all(math.isfinite(v) for v in self.target):
            raise ValueError(f"step {self.label!r}: target must be {count} finite numbers, got {self.target}")
        if isinstance(self.n_increments, bool) or int(self.n_increments) != self.n_increments or self.n_increments < 1:
            raise ValueError(f"step {self.label!r}: n_increments = {self.n_increments} must be an integer >= 1")
        if self.n_increments > MAX_INCREMENTS:
            raise ValueError(f"step {self.label!r}: {self.n_increments:g} increments, more than {MAX_INCREMENTS:g} (an "
                             f"increment too small for its strain?)")
        object.__setattr__(self, "n_increments", int(self.n_increments))
        if not self.label or not self.label.isidentifier():
            raise ValueError(f"step label {self.label!r} must be a non-empty identifier (letters, digits, _)")
        for comp, control, value in zip(dimension_of(self.dim).normal_components, self.control, self.target):
            if control == "strain" and not abs(value) < 1.0:
                raise ValueError(f"step {self.label!r}: strain change of component {comp} = {value:g} must be in (-1, 1)")
        if self.stop_at_p is not None:
            object.__setattr__(self, "stop_at_p", float(self.stop_at_p))
            if any(c != "strain" for c in self.control):
                raise ValueError(f"step {self.label!r}: stop_at_p needs strain control on "
                                 f"{dimension_of(self.dim).every_axis} components")
            if not (math.isfinite(self.stop_at_p) and self.stop_at_p > 0.0):
                raise ValueError(f"step {self.label!r}: stop_at_p = {self.stop_at_p:g} must be finite and > 0")
            if sum(self.target) <= 0.0:
                raise ValueError(f"step {self.label!r}: stop_at_p needs a contracting strain path (target sum > 0)")
        if self.coupling is not None:
            object.__setattr__(self, "coupling", tuple(float(v) for v in self.coupling))
            if len(self.coupling) != self.dim or not all(math.isfinite(v) for v in self.coupling):
                raise ValueError(f"step {self.label!r}: coupling must be {self.dim} finite numbers, got {self.coupling}")
            if self.control[0] != "strain" or self.coupling[0] != 0.0:
                raise ValueError(f"step {self.label!r}: coupling needs strain control of component 11 and coupling[0] = 0")
            if any(v != 0.0 for c, v in zip(self.control, self.coupling) if c == "strain"):
                raise ValueError(f"step {self.label!r}: coupling applies to stress-controlled components only")

    @property
    def dim(self) -> int:
        """Number of controlled normal components: 2 (plane strain) or 3 (triaxial)."""
        return len(self.control)

    @property
    def stress_mask(self) -> tuple[bool, ...]:
        """Per component: True where stress-controlled."""
        return tuple(c == "stress" for c in self.control)


Programme = tuple[Step, ...]
"""A loading programme: steps run in order."""


def validate(programme: Programme) -> Programme:
    """Return ``programme`` as a tuple if it is a non-empty sequence of ``Step`` of one dimension; else ValueError."""
    programme = tuple(programme)
    if not programme:
        raise ValueError("a loading programme needs at least one step")
    for item in programme:
        if not isinstance(item, Step):
            raise ValueError(f"programme items must be Step, got {type(item).__name__}")
    dims = sorted({item.dim for item in programme})
    if len(dims) > 1:
        raise ValueError(f"a loading programme has steps of one dimension, got steps of {' and '.join(map(str, dims))} components")
    return programme


def dimension(programme: Programme) -> int:
    """Number of controlled components of the steps of ``programme`` (2 or 3)."""
    return validate(programme)[0].dim


def n_increments_for(strain: float, increment: float) -> int:
    """Number of increments of size ``increment`` [-] that cover ``strain`` [-] (at least 1, at most
    ``MAX_INCREMENTS``: ValueError beyond)."""
    if not (increment > 0.0 and math.isfinite(increment)):
        raise ValueError(f"increment = {increment:g} must be finite and > 0")
    count = abs(strain) / increment
    if count > MAX_INCREMENTS:
        raise ValueError(f"increment {increment:g} cuts the strain {strain:g} into {count:.3g} increments, more than "
                         f"{MAX_INCREMENTS:g}")
    return max(1, round(count))


def isotropic(
    p0: float,
    *,
    increment: float = LoadingDefaults.iso_increment,
    max_strain: float = ISO_MAX_STRAIN,
    label: str = "iso",
    dim: int = 2,
) -> Step:
    """Isotropic compression: equal strain increments on every normal component until p = p0.

    Args:
        p0: confining pressure to reach [N/m in 2D, Pa in 3D], > 0, compression positive.
        increment: strain increment per component [-].
        max_strain: strain per component after which the stage fails if p < p0 [-].
        label: stage label.
        dim: 2 (components 11, 22) or 3 (11, 22, 33).
    """
    n = n_increments_for(max_strain, increment)
    return Step(("strain",) * dim, (n * increment,) * dim, n, label, stop_at_p=p0)


def constant_volume_biaxial(eps1_end: float, n_increments: int, *, label: str = "shear") -> Step:
    """Constant-volume ("undrained") biaxial shear: d_eps11 = +delta, d_eps22 = -delta.

    Args:
        eps1_end: axial strain at the end of the step, counted from its start [-].
        n_increments: number of increments (delta = eps1_end / n_increments).
        label: stage label.
    """
    return Step(("strain", "strain"), (eps1_end, -eps1_end), n_increments, label)


def drained_biaxial(sigma22: float, eps1_end: float, n_increments: int, *, label: str = "shear") -> Step:
    """Drained biaxial shear: eps11 strain-controlled, sigma22 held at ``sigma22`` [N/m].

    Args:
        sigma22: lateral stress to hold [N/m], compression positive.
        eps1_end: axial strain at the end of the step, counted from its start [-].
        n_increments: number of increments.
        label: stage label.
    """
    return Step(("strain", "stress"), (eps1_end, sigma22), n_increments, label)


def proportional_strain(d_eps11: float, d_eps22: float, n_increments: int, *, label: str = "shear") -> Step:
    """Proportional strain path: strain changes (d_eps11, d_eps22) [-] over ``n_increments``."""
    return Step(("strain", "strain"), (d_eps11, d_eps22), n_increments, label)


def biaxial(
    p0: float,
    eps1_end: float,
    increment: float,
    *,
    iso_increment: float = LoadingDefaults.iso_increment,
    drained: bool = False,
) -> Programme:
    """Isotropic compression to p0, then constant-volume (or drained, sigma22 = p0) shear.

    Args:
        p0: confining pressure [N/m], > 0.
        eps1_end: axial strain of the shear stage, counted from its start [-], > 0.
        increment: axial strain increment of the shear stage [-], > 0.
        iso_increment: strain increment per component of the isotropic stage [-], > 0.
        drained: hold sigma22 = p0 instead of constant volume.
    """
    if not (math.isfinite(p0) and p0 > 0.0):
        raise ValueError(f"p0 = {p0:g} must be finite and > 0")
    if not (math.isfinite(eps1_end) and eps1_end > 0.0):
        raise ValueError(f"eps1_end = {eps1_end:g} must be finite and > 0")
    n = n_increments_for(eps1_end, increment)
    shear = drained_biaxial(p0, eps1_end, n) if drained else constant_volume_biaxial(eps1_end, n)
    return (isotropic(p0, increment=iso_increment), shear)


TRIAXIAL_TESTS = ("undrained", "drained", "extension", "constant_p", "true", "cyclic")
"""Shear stages of ``triaxial``: undrained (isochoric) compression, drained compression and
extension at constant sigma3, compression at constant p, true triaxial at constant p and b, cyclic undrained."""


def triaxial_shear(test: str, p0: float, eps_max: float, n_increments: int, *, b: float = 0.5,
                   cycles: int = 2, label: str = "shear") -> Programme:
    """The shear stage(s) of a triaxial test from the isotropic state p0 (axis 1 axial).

    Args:
        test: one of ``TRIAXIAL_TESTS``:
            ``undrained``: d_eps = (+d, -d/2, -d/2), constant volume;
            ``drained``: axial strain +eps_max, sigma22 = sigma33 = p0;
            ``extension``: axial strain -eps_max, sigma22 = sigma33 = p0;
            ``constant_p``: axial strain +eps_max, sigma22 = sigma33, p = p0 (coupling -1/2);
            ``true``: axial strain +eps_max, p = p0 and b held (``true_triaxial_coupling``);
            ``cyclic``: ``cycles`` undrained cycles of axial strain amplitude eps_max
            (0 -> +eps_max -> -eps_max -> 0 per cycle).
        p0: isotropic stress at the start [Pa], > 0.
        eps_max: axial strain (amplitude) [-], > 0.
        n_increments: increments per eps_max of axial strain.
        b: intermediate-stress ratio of ``true``, in [0, 1].
        cycles: number of cycles of ``cyclic``, >= 1.
        label: stage label of every step.
    """
    if test not in TRIAXIAL_TESTS:
        raise ValueError(f"unknown triaxial test {test!r}; choose from {', '.join(TRIAXIAL_TESTS)}")
    n = n_increments
    if test == "undrained":
        return (isochoric(eps_max, n, label=label),)
    if test == "cyclic":
        if int(cycles) < 1:
            raise ValueError(f"cycles = {cycles} must be >= 1")
        legs = [(eps_max, n)] + [(-2.0 * eps_max, 2 * n), (2.0 * eps_max, 2 * n)] * int(cycles)
        legs[-1] = (eps_max, n)
        return tuple(isochoric(e, k, label=label) for e, k in legs)
    control = ("strain", "stress", "stress")
    if test in ("drained", "extension"):
        return (Step(control, (eps_max if test == "drained" else -eps_max, p0, p0), n, label),)
    if test == "constant_p":
        return (Step(control, (eps_max, p0, p0), n, label, coupling=(0.0, -0.5, -0.5)),)
    if not 0.0 <= b <= 1.0:
        raise ValueError(f"b = {b:g} must be in [0, 1]")
    return (Step(control, (eps_max, p0, p0), n, label, coupling=true_triaxial_coupling(b)),)


def true_triaxial_coupling(b: float) -> tuple[float, float, float]:
    """Coupling that holds p and b = (sigma2 - sigma3) / (sigma1 - sigma3) from an isotropic state:
    d sigma22 = (2b - 1) / (2 - b) d sigma11, d sigma33 = -(1 + b) / (2 - b) d sigma11 (their sum is -d sigma11)."""
    return (0.0, (2.0 * b - 1.0) / (2.0 - b), -(1.0 + b) / (2.0 - b))


def isochoric(eps_axial: float, n_increments: int, *, label: str = "shear") -> Step:
    """Undrained (isochoric) triaxial step: axial strain ``eps_axial`` [-] in ``n_increments`` equal
    increments d, lateral increments d_lat = 1 - 1 / sqrt(1 - d) each, so that every increment
    keeps (1 - d)(1 - d_lat)^2 = 1 (the volume V = V0 J of the driver, to rounding)."""
    d = eps_axial / n_increments
    d_lat = dimension_of(3).undrained_lateral(d)
    return Step(("strain",) * 3, (eps_axial, n_increments * d_lat, n_increments * d_lat), n_increments, label)


def triaxial(
    p0: float,
    eps_max: float,
    increment: float,
    *,
    test: str = "undrained",
    iso_increment: float = LoadingDefaults.iso_increment,
    b: float = 0.5,
    cycles: int = 2,
) -> Programme:
    """Isotropic compression to p0 (three equal strain components), then the shear of ``test``
    (``triaxial_shear``); strains [-], stresses [Pa], compression positive."""
    if not (math.isfinite(p0) and p0 > 0.0):
        raise ValueError(f"p0 = {p0:g} must be finite and > 0")
    if not (math.isfinite(eps_max) and eps_max > 0.0):
        raise ValueError(f"eps_max = {eps_max:g} must be finite and > 0")
    n = n_increments_for(eps_max, increment)
    return (isotropic(p0, increment=iso_increment, dim=3),
            *triaxial_shear(test, p0, eps_max, n, b=b, cycles=cycles))


def oedometric(
    p0: float,
    eps_load: float,
    eps_unload: float,
    increment: float,
    *,
    iso_increment: float = LoadingDefaults.iso_increment,
) -> Programme:
    """Oedometric (K0) test under pure strain control: isotropic compression to the seating stress p0,
    then axial loading by ``eps_load`` and unloading by ``eps_unload`` of axial strain with the lateral
    strains 22 and 33 held at zero (steps ``load`` and ``unload``; no unloading step when it is 0).

    Args:
        p0: isotropic seating stress [Pa], > 0.
        eps_load: axial strain of the loading step [-], > 0 (compression positive).
        eps_unload: axial strain recovered by the unloading step [-], in [0, eps_load].
        increment: axial strain increment of both steps [-].
        iso_increment: strain increment per component of the isotropic stage [-].
    """
    if not (math.isfinite(p0) and p0 > 0.0):
        raise ValueError(f"p0 = {p0:g} must be finite and > 0")
    if not (math.isfinite(eps_load) and eps_load > 0.0):
        raise ValueError(f"oedometric loading strain = {eps_load:g} must be finite and > 0")
    if not (math.isfinite(eps_unload) and 0.0 <= eps_unload <= eps_load):
        raise ValueError(f"oedometric unloading strain = {eps_unload:g} must be in [0, {eps_load:g}] (the loading strain)")
    control = ("strain",) * 3
    steps = [isotropic(p0, increment=iso_increment, dim=3),
             Step(control, (eps_load, 0.0, 0.0), n_increments_for(eps_load, increment), "load")]
    if eps_unload > 0.0:
        steps.append(Step(control, (-eps_unload, 0.0, 0.0), n_increments_for(eps_unload, increment), "unload"))
    return tuple(steps)


def _step_dict(step: Step) -> dict[str, Any]:
    data = {**asdict(step), "control": list(step.control), "target": list(step.target)}
    if step.coupling is None:
        del data["coupling"]  # planar programmes keep their stored form
    else:
        data["coupling"] = list(step.coupling)
    return data


def to_dict(programme: Programme) -> dict[str, Any]:
    """JSON-compatible description of ``programme`` (inverse: ``from_dict``); ``coupling`` only where set."""
    return {"steps": [_step_dict(s) for s in validate(programme)]}


PROGRAMME_KEYS = ("steps",)
"""Keys of a programme description (``to_dict``)."""
STEP_KEYS = tuple(f.name for f in fields(Step))
"""Keys of one step: the fields of ``Step``."""


class UnknownKey(ValueError):
    """A key of a programme description that nothing reads; the message is one line and names it."""


def _check_keys(keys: Any, where: str, expected: Sequence[str]) -> None:
    for key in keys:
        if key not in expected:
            close = difflib.get_close_matches(str(key), expected, n=1, cutoff=0.75)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise UnknownKey(f"unknown key {key!r} {where}{hint}; expected one of: {', '.join(expected)}")


def from_dict(data: Mapping[str, Any], source: str | None = None) -> Programme:
    """Programme described by ``data`` (as made by ``to_dict``); ValueError (one line) if malformed.

    A key that nothing reads (not in ``PROGRAMME_KEYS`` or ``STEP_KEYS``) is refused with its name
    and where it is (``UnknownKey``; ``source``, e.g. the file, ends the place), so that a
    misspelt key is never silently ignored.
    """
    of = f" of {source}" if source else ""
    try:
        _check_keys(data, f"at the top level{of}", PROGRAMME_KEYS)
        steps = data["steps"]
        for number, step in enumerate(steps, start=1):
            if not isinstance(step, Mapping):
                raise ValueError(f"step {number} is not a table of keys ({', '.join(STEP_KEYS)})")
            _check_keys(step, f"in step {number}{of}", STEP_KEYS)
        return validate(tuple(Step(**dict(s)) for s in steps))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"malformed loading programme: {exc}") from None


PROGRAMME_SUFFIXES = (".json", ".toml")
"""File formats of ``read_programme``, by suffix."""


def read_programme(path: Path) -> Programme:
    """Programme stored in the JSON or TOML file ``path`` in the format of ``to_dict``.

    JSON: ``{"steps": [{"control": [...], "target": [...], "n_increments": n, "label": "..."}, ...]}``;
    TOML: one ``[[steps]]`` table per step with the same keys. ``stop_at_p`` is optional.

    Raises:
        ValueError: one line naming the file, for a missing, unreadable or malformed file, or
            one with a key that nothing reads (``UnknownKey``).
    """
    path = Path(path)
    if path.suffix.lower() not in PROGRAMME_SUFFIXES:
        raise ValueError(f"{path}: a programme file ends in {' or '.join(PROGRAMME_SUFFIXES)}")
    if not path.is_file():
        raise ValueError(f"{path}: no such programme file")
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read programme: {exc}") from None
    if not isinstance(data, Mapping) or not isinstance(data.get("steps"), list):
        raise ValueError(f"{path}: a programme needs a list of steps ('steps' array / [[steps]] tables)")
    try:
        return from_dict(data, source=str(path))
    except UnknownKey:
        raise
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
