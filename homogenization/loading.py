"""Loading programmes as data: mixed strain/stress control per component (spec section 9).

A ``Programme`` is a tuple of ``Step``s run one after the other by ``driver.run``. Each step
controls the two normal components in the order (11, 22), each by ``"strain"`` or
``"stress"``; the macro shear strain increment is always zero.

- A strain-controlled component changes by ``target`` [-] over the step, in
  ``n_increments`` equal increments (the target counts from the start of the step).
- A stress-controlled component ends the step at sigma = ``target`` [N/m]; the driver ramps
  it linearly from its value at the start of the step and solves the strain that gives it.
- ``stop_at_p`` (only with strain control on both components): the step ends as soon as the
  mean stress p reaches ``stop_at_p`` [N/m]; the increment that would cross it is shortened
  (its strain increment scaled by a factor in (0, 1] solved by the driver) so that p lands
  on ``stop_at_p`` within the stress tolerance. Reaching the last increment first is an
  error. This is how the isotropic stage reaches p0 exactly while staying strain-driven.

Sign convention: compression and contraction positive (strains [-], stresses [N/m]).
``to_dict``/``from_dict`` round-trip a programme through JSON-compatible data (stored in the
HDF5 attributes of a run); ``read_programme`` reads the same data from a JSON or TOML file
(``hmodel biaxial --programme FILE``; format and examples in docs/programmes.md, example
files in homogenization/data/programmes/).
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

from warp_hcell.core.parameters import LoadingDefaults

CONTROLS = ("strain", "stress")
"""Allowed control kinds of a component."""
COMPONENTS = ("11", "22")
"""Controlled components, in the order of ``Step.control`` and ``Step.target``."""
ISO_MAX_STRAIN = 0.1
"""Largest strain per component the isotropic stage may apply before giving up [-]."""


@dataclass(frozen=True)
class Step:
    """One stage of a loading programme; validated on construction (one-line ValueError)."""

    control: tuple[str, str]
    """Control of components (11, 22): each "strain" or "stress"."""
    target: tuple[float, float]
    """Per component: strain change over the step [-] (strain control) or the stress at the
    end of the step [N/m] (stress control); compression positive."""
    n_increments: int
    """Number of increments of the step (an upper bound when ``stop_at_p`` is set)."""
    label: str
    """Stage label written to outputs (e.g. "iso", "shear")."""
    stop_at_p: float | None = None
    """End the step once p reaches this mean stress [N/m] (strain control only)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "control", tuple(self.control))
        object.__setattr__(self, "target", tuple(float(v) for v in self.target))
        if len(self.control) != 2 or any(c not in CONTROLS for c in self.control):
            raise ValueError(f"step {self.label!r}: control must be two of {CONTROLS}, got {self.control}")
        if len(self.target) != 2 or not all(math.isfinite(v) for v in self.target):
            raise ValueError(f"step {self.label!r}: target must be two finite numbers, got {self.target}")
        if isinstance(self.n_increments, bool) or int(self.n_increments) != self.n_increments or self.n_increments < 1:
            raise ValueError(f"step {self.label!r}: n_increments = {self.n_increments} must be an integer >= 1")
        object.__setattr__(self, "n_increments", int(self.n_increments))
        if not self.label or not self.label.isidentifier():
            raise ValueError(f"step label {self.label!r} must be a non-empty identifier (letters, digits, _)")
        for comp, control, value in zip(COMPONENTS, self.control, self.target):
            if control == "strain" and not abs(value) < 1.0:
                raise ValueError(f"step {self.label!r}: strain change of component {comp} = {value:g} must be in (-1, 1)")
        if self.stop_at_p is not None:
            object.__setattr__(self, "stop_at_p", float(self.stop_at_p))
            if self.control != ("strain", "strain"):
                raise ValueError(f"step {self.label!r}: stop_at_p needs strain control on both components")
            if not (math.isfinite(self.stop_at_p) and self.stop_at_p > 0.0):
                raise ValueError(f"step {self.label!r}: stop_at_p = {self.stop_at_p:g} must be finite and > 0")
            if self.target[0] + self.target[1] <= 0.0:
                raise ValueError(f"step {self.label!r}: stop_at_p needs a contracting strain path (target sum > 0)")

    @property
    def stress_mask(self) -> tuple[bool, bool]:
        """Per component (11, 22): True where stress-controlled."""
        return (self.control[0] == "stress", self.control[1] == "stress")


Programme = tuple[Step, ...]
"""A loading programme: steps run in order."""


def validate(programme: Programme) -> Programme:
    """Return ``programme`` as a tuple if it is a non-empty sequence of ``Step``; else ValueError."""
    programme = tuple(programme)
    if not programme:
        raise ValueError("a loading programme needs at least one step")
    for item in programme:
        if not isinstance(item, Step):
            raise ValueError(f"programme items must be Step, got {type(item).__name__}")
    return programme


def n_increments_for(strain: float, increment: float) -> int:
    """Number of increments of size ``increment`` [-] that cover ``strain`` [-] (at least 1)."""
    if not (increment > 0.0 and math.isfinite(increment)):
        raise ValueError(f"increment = {increment:g} must be finite and > 0")
    return max(1, round(abs(strain) / increment))


def isotropic(
    p0: float,
    *,
    increment: float = LoadingDefaults.iso_increment,
    max_strain: float = ISO_MAX_STRAIN,
    label: str = "iso",
) -> Step:
    """Isotropic compression: equal strain increments on 11 and 22 until p = p0.

    Args:
        p0: confining pressure to reach [N/m], > 0, compression positive.
        increment: strain increment per component [-].
        max_strain: strain per component after which the stage fails if p < p0 [-].
        label: stage label.
    """
    n = n_increments_for(max_strain, increment)
    return Step(("strain", "strain"), (n * increment, n * increment), n, label, stop_at_p=p0)


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


def to_dict(programme: Programme) -> dict[str, Any]:
    """JSON-compatible description of ``programme`` (inverse: ``from_dict``)."""
    return {"steps": [{**asdict(s), "control": list(s.control), "target": list(s.target)} for s in validate(programme)]}


def from_dict(data: Mapping[str, Any]) -> Programme:
    """Programme described by ``data`` (as made by ``to_dict``); ValueError if malformed."""
    try:
        steps = data["steps"]
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
        ValueError: one line naming the file, for a missing, unreadable or malformed file.
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
        return from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
