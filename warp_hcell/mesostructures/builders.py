"""Parametric mesostructures: H-cells with unequal grains and fine grains in the pore, and specs.

A mesostructure is named on the command line (``--mesostructure``) and in Python either by a
file (TOML/JSON, ``warp_hcell.mesostructures.files.load_mesostructure``) or by a *builder spec*:

    SPEC   := KIND [":" KEY "=" VALUE ("," KEY "=" VALUE)*]
    KIND   := "hcell" | "hcell-unequal" | "hcell-fines" | "hcell3d" | "hcell3d-fines" | "hcell3d-axisym" | "hcell3d-sand"

Keys (all optional unless marked):

- ``alpha0=DEG``: initial opening angle [deg], in [30, 90); without it the command's
  ``--alpha0`` (or the sweep's list) is used.
- ``radius=R``: radius r of the axial grains 1 and 4 [m] (default 0.5).
- ``lateral=RATIO``: radius of the lateral grains over r [-] (default 1; required by
  ``hcell-unequal``).
- ``ratio=R1/R2/...``: fine grains (required by ``hcell-fines``): radius of each over r [-];
  0 means no grain. Fine grains are free (no driven DOF), labelled 7, 8, ...
- ``n=X1/X2/...``, ``t=Y1/Y2/...`` (3D: ``t1``, ``t2``): offset of each fine grain's centre from
  the pore centre in units of r [-] (default 0); one value applies to every grain.
- ``plane=DEG`` (``hcell3d``): angle between the ten-sphere cell's two planes (default 90).

Examples: ``hcell``, ``hcell-unequal:alpha0=55,lateral=0.7``, ``hcell-fines:ratio=0.3/0.3,n=0.4/-0.4``,
``hcell3d:alpha0=55``, ``hcell3d-fines:ratio=0.5,n=0.1``, ``hcell3d-axisym:alpha0=54`` (driven by
the axisymmetric part of the strain; docs/model.md section 14), ``hcell3d-sand:alpha0=54`` (the
same with the cell's deviator doubled, kinematics "amplified"; docs/triaxial.md). Anything that is not a spec is a
file path (``./hcell`` for a file of that name). In a comma list (the sweep), a piece
``KEY=VALUE`` without ``:`` continues the spec before it (``split_mesostructure_list``).

Raises ``MesostructureError`` (one line) for an unknown kind or key, malformed values, and what
``warp_hcell.mesostructures.hcell.build_h_cell`` refuses (overlapping grains, a fine grain
outside the pore; ``hcell.pore_ratio`` gives the largest that fits).

This module parses names; cells are built by ``warp_hcell.mesostructures.hcell`` (the only code
that knows their shape) or read by ``warp_hcell.mesostructures.files``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from warp_hcell.core.parameters import CellDefaults, check_alpha0_deg
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.hcell import build_h_cell, build_h_cell_3d
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES, Mesostructure, MesostructureError

KINDS = ("hcell", "hcell-unequal", "hcell-fines", "hcell3d", "hcell3d-fines", "hcell3d-axisym", "hcell3d-sand")
"""Builder names accepted as the KIND of a spec."""
KEYS = {
    "hcell": ("alpha0", "radius", "lateral"),
    "hcell-unequal": ("alpha0", "radius", "lateral"),
    "hcell-fines": ("alpha0", "radius", "lateral", "ratio", "n", "t"),
    "hcell3d": ("alpha0", "radius", "lateral", "plane"),
    "hcell3d-fines": ("alpha0", "radius", "lateral", "plane", "ratio", "n", "t1", "t2"),
    "hcell3d-axisym": ("alpha0", "radius", "lateral", "plane"),
    "hcell3d-sand": ("alpha0", "radius", "lateral", "plane"),
}
"""Keys each kind accepts."""
REQUIRED = {"hcell": (), "hcell-unequal": ("lateral",), "hcell-fines": ("ratio",), "hcell3d": (),
            "hcell3d-fines": ("ratio",), "hcell3d-axisym": (), "hcell3d-sand": ()}
"""Keys each kind needs."""
KIND_KINEMATICS = {"hcell3d-axisym": "axisymmetric", "hcell3d-sand": "amplified"}
"""Kinematics of the 3D kinds not driven by the projected strains (``hcell.KINEMATICS_GAIN``)."""
LIST_KEYS = ("ratio", "n", "t", "t1", "t2")
"""Keys whose value is a "/"-separated list (one value per fine grain)."""
@dataclass(frozen=True)
class MesostructureSource:
    """A mesostructure as named by the user: a builder spec or a file, not yet built.

    Attributes:
        text: the text as given (spec or path).
        kind: builder name (one of ``KINDS``), or None for a file.
        options: parsed spec keys -> values (floats, or tuples of floats for list keys).
    """

    text: str
    kind: str | None
    options: tuple[tuple[str, float | tuple[float, ...]], ...] = ()

    @property
    def fixed_alpha0(self) -> float | None:
        """alpha0 [deg] fixed by the spec, or None (files, and specs without alpha0)."""
        return dict(self.options).get("alpha0")  # type: ignore[return-value]

    @property
    def takes_alpha0(self) -> bool:
        """True for a spec whose alpha0 comes from the command (a file fixes its geometry)."""
        return self.kind is not None and self.fixed_alpha0 is None

    @property
    def label(self) -> str:
        """Short name for folders and legends: the spec text, or the file's stem."""
        return self.text if self.kind is not None else Path(self.text).stem

    def build(self, alpha0_deg: float | None = None, radius: float | None = None) -> Mesostructure:
        """The mesostructure; ``alpha0_deg`` [deg] and ``radius`` [m] are used by specs without their own
        alpha0 and radius (None: the defaults).

        Raises:
            MesostructureError: unreadable file or invalid geometry (one line).
        """
        if self.kind is None:
            return load_mesostructure(self.text)
        opts: Mapping[str, float | tuple[float, ...]] = dict(self.options)
        alpha0 = opts.get("alpha0", CellDefaults.alpha0_deg if alpha0_deg is None else alpha0_deg)
        fines = tuple(opts.get("ratio", ()))  # type: ignore[arg-type]
        n_fines = len(fines)
        spatial = self.kind.startswith("hcell3d")
        offsets = None
        if n_fines:
            axes = AXIS_NAMES[3 if spatial else 2]
            offsets = tuple(zip(*(_per_grain(self.text, key, opts.get(key, (0.0,)), n_fines) for key in axes)))
        size = {"radius": float(opts.get("radius", CellDefaults.radius if radius is None else radius)),  # type: ignore[arg-type]
                "lateral": float(opts.get("lateral", 1.0))}  # type: ignore[arg-type]
        if spatial:
            return build_h_cell_3d(float(alpha0), **size, plane_angle_deg=float(opts.get("plane", 90.0)),  # type: ignore[arg-type]
                                   fines=fines, fine_offsets=offsets, name=self.text,
                                   kinematics=KIND_KINEMATICS.get(self.kind, "projected"))
        return build_h_cell(float(alpha0), **size, fines=fines, fine_offsets=offsets, name=self.text)

    def __str__(self) -> str:
        return self.text


def _per_grain(text: str, key: str, values, n_fines: int) -> tuple[float, ...]:
    values = tuple(values)
    if len(values) == 1:
        return values * n_fines
    if len(values) != n_fines:
        raise MesostructureError(f"mesostructure {text!r}: {key} has {len(values)} values for {n_fines} fine grains")
    return values


def parse_mesostructure(text: str) -> MesostructureSource:
    """Parse a spec (grammar in the module docstring) or take ``text`` as a file path.

    Only the syntax is checked here (and that a file exists); ``build`` validates geometry.

    Raises:
        MesostructureError: malformed spec, or a path that is not a file (one line).
    """
    text = str(text).strip()
    kind, _, body = text.partition(":")
    if kind in KINDS:
        options: dict[str, float | tuple[float, ...]] = {}
        for item in filter(None, (piece.strip() for piece in body.split(","))):
            key, sep, value = (part.strip() for part in item.partition("="))
            if not sep or not value:
                raise MesostructureError(f"mesostructure {text!r}: {item!r} is not KEY=VALUE")
            if key not in KEYS[kind]:
                raise MesostructureError(f"mesostructure {text!r}: unknown key {key!r} for {kind}; "
                                         f"allowed: {', '.join(KEYS[kind])}")
            if key in options:
                raise MesostructureError(f"mesostructure {text!r}: key {key!r} given twice")
            try:
                numbers = tuple(float(v) for v in value.split("/"))
            except ValueError:
                raise MesostructureError(f"mesostructure {text!r}: {key}={value!r} is not a number"
                                         + (" list (a/b/...)" if key in LIST_KEYS else "")) from None
            if not all(math.isfinite(v) for v in numbers):
                raise MesostructureError(f"mesostructure {text!r}: {key}={value!r} is not finite")
            if key not in LIST_KEYS and len(numbers) != 1:
                raise MesostructureError(f"mesostructure {text!r}: {key} takes one value, got {value!r}")
            options[key] = numbers if key in LIST_KEYS else numbers[0]
        missing = [key for key in REQUIRED[kind] if key not in options]
        if missing:
            raise MesostructureError(f"mesostructure {text!r}: {kind} needs {missing[0]}=...")
        if "alpha0" in options:
            try:
                check_alpha0_deg(options["alpha0"])  # type: ignore[arg-type]
            except ValueError as exc:
                raise MesostructureError(f"mesostructure {text!r}: {exc}") from None
        return MesostructureSource(text, kind, tuple(options.items()))
    if not Path(text).is_file():
        raise MesostructureError(f"mesostructure {text!r} is neither a file nor a spec ({' | '.join(KINDS)}[:KEY=VALUE,...])")
    return MesostructureSource(text, None)


def resolve_mesostructure(text: str, alpha0_deg: float | None = None) -> Mesostructure:
    """The mesostructure named by ``text`` (file path or spec), built at ``alpha0_deg`` if it needs one."""
    return parse_mesostructure(text).build(alpha0_deg)


def split_mesostructure_list(text: str) -> list[str]:
    """Split a comma list of mesostructures; a ``KEY=VALUE`` piece without ``:`` joins the spec before it.

    ``"hcell,hcell-fines:alpha0=50,ratio=0.7,data/x.toml"`` -> ``["hcell",
    "hcell-fines:alpha0=50,ratio=0.7", "data/x.toml"]``.
    """
    items: list[str] = []
    for piece in (p.strip() for p in str(text).split(",")):
        if not piece:
            continue
        continues = "=" in piece and ":" not in piece and items and items[-1].partition(":")[0] in KINDS
        if continues:
            items[-1] = f"{items[-1]},{piece}" if ":" in items[-1] else f"{items[-1]}:{piece}"
        else:
            items.append(piece)
    return items


def mesostructure_arg(text: str) -> MesostructureSource:
    """argparse type: a spec or a file (see the module docstring); one-line error otherwise."""
    try:
        return parse_mesostructure(text)
    except MesostructureError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def mesostructure_list_arg(text: str) -> list[MesostructureSource]:
    """argparse type: comma list of specs and files (``split_mesostructure_list``)."""
    items = split_mesostructure_list(text)
    if not items:
        raise argparse.ArgumentTypeError("empty mesostructure list")
    return [mesostructure_arg(item) for item in items]


MESOSTRUCTURE_HELP = (
    "mesostructure: a TOML/JSON file, or a builder spec KIND[:KEY=VALUE,...] with KIND hcell | hcell-unequal | "
    "hcell-fines (2D) or hcell3d | hcell3d-fines | hcell3d-axisym | hcell3d-sand (3D, ten spheres) and keys alpha0 (deg; default: the command's --alpha0, where it has one), "
    "radius (r of grains 1, 4 [m]), lateral (radius of the lateral grains / r), plane (3D: angle between the two "
    "planes, deg), ratio (fine-grain radius / r, 'a/b' for several), n, t (2D) or n, t1, t2 (3D) (fine-grain "
    "offset from the pore centre / r); e.g. hcell-fines:alpha0=50,ratio=0.76 or hcell3d:alpha0=55")
"""--help text shared by every command that takes --mesostructure."""
