"""Mesostructures from files, descriptions and state arrays; the labels they carry declare the rest.

- ``load_mesostructure(path)``: a TOML or JSON description (format in its docstring;
  examples in ``warp_hcell/data``);
- ``describe(meso)`` / ``from_description(text)`` / ``description_sha256(text)``: canonical
  JSON text of a mesostructure (stored in databases and checkpoints), its inverse, and its hash;
- ``with_declarations(meso)``: ``meso`` with the observables and parameters its pair labels
  declare. Files, descriptions and state arrays carry labels only; the builder that defines
  them (``warp_hcell.mesostructures.hcell``) declares what they mean.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import tomllib
from dataclasses import replace
from itertools import combinations
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from warp_hcell.core.parameters import DemSettings
from warp_hcell.mesostructures import hcell
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES, LABEL_KEY, Mesostructure, MesostructureError


def with_declarations(meso: Mesostructure) -> Mesostructure:
    """``meso`` with the observables and parameters that its pair labels declare (``hcell.declare``)."""
    return hcell.declare(meso)


def load_mesostructure(path: str | Path, *, contact_tolerance: float = DemSettings.contact_tolerance) -> Mesostructure:
    """Read a mesostructure from a TOML (``.toml``) or JSON (``.json``) file.

    Format (labels 1-based, coordinates (n, t) in metres)::

        name = "h-cell, lateral grains 0.7 D"
        cell_size = [l1_ref, l2_ref]
        outer = [1, 2, 3, 4, 5, 6]          # ordered polygon whose area is V_cell
        pairs = [[1, 2], ...]               # optional; default: all pairs (touching grains must be one)
        type1 = [[1, 2], [1, 6], ...]       # optional H-cell labels (``hcell.file_labels``)
        type2 = [[2, 3], [5, 6]]
        [[grains]]                          # one table per grain, in label order
        radius = 0.5
        position = [x_n, x_t]
        driven = [true, false]              # (along n, along t)

    3D: three coordinates per grain, three cell lengths, ``outer`` the outward triangles of the
    closed surface ([[1, 6, 10], ...]), optionally ``kinematics = "axisymmetric"``
    (``KINEMATICS``). Any other key is refused with its name (``check_keys``).

    Raises:
        MesostructureError: unreadable file, unknown key or invalid description (one line)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # (a byte-order mark is taken off)
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except UnicodeDecodeError as exc:
        raise MesostructureError(f"cannot read mesostructure file {path}: not UTF-8 text (byte {exc.start} is "
                                 f"0x{exc.object[exc.start]:02x})") from None
    except OSError as exc:
        raise MesostructureError(f"cannot read mesostructure file {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise MesostructureError(f"mesostructure file {path} is not valid {path.suffix[1:].upper()}: {exc}") from None
    check_keys(data, path)
    return _from_mapping(data, default_name=path.stem, contact_tolerance=contact_tolerance)


FILE_KEYS = ("name", "cell_size", "outer", "pairs", *hcell.FILE_LABEL_KEYS, "grains", "kinematics")
"""Keys of a mesostructure file (``hcell.FILE_LABEL_KEYS``: the H-cell labels read by ``hcell.file_labels``)."""
GRAIN_KEYS = ("radius", "position", "driven")
"""Keys of one grain of a mesostructure file."""
KINEMATICS = ("projected", *hcell.KINEMATICS_GAIN)
"""Values of the ``kinematics`` key of a 3D cell's file or description: how the macro strain drives the
cell (homogenization.material.orientation); "axisymmetric" and "amplified" set the parameter
``hcell.AXISYMMETRIC_KINEMATICS`` to their ``hcell.KINEMATICS_GAIN``."""


def _with_kinematics(meso: Mesostructure, kinematics: Any, where: str) -> Mesostructure:
    """``meso`` with the parameter of the ``kinematics`` read from a file or description ``where``."""
    if kinematics is None or kinematics == "projected":
        return meso
    if kinematics not in hcell.KINEMATICS_GAIN:
        raise MesostructureError(f"{where}: kinematics = {kinematics!r} is not one of {', '.join(KINEMATICS)}")
    if meso.dim != 3:
        raise MesostructureError(f"{where}: kinematics = {kinematics!r} needs a 3D cell")
    return replace(meso, parameters={**meso.parameters,
                                     hcell.AXISYMMETRIC_KINEMATICS: hcell.KINEMATICS_GAIN[kinematics]})


def unknown_key_message(key: str, where: str, path: str | Path, expected: tuple[str, ...]) -> str:
    """One line naming an unknown ``key`` found ``where`` in the file ``path``, the closest
    expected key and all of ``expected``."""
    close = difflib.get_close_matches(key, expected, n=1, cutoff=0.75)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown key {key!r} {where} of {path}{hint}; expected one of: {', '.join(expected)}"


def check_keys(data: Any, path: str | Path) -> None:
    """MesostructureError (one line) for a key of a mesostructure file that nothing reads: at the
    top level (``FILE_KEYS``) or in a grain (``GRAIN_KEYS``), so that a misspelt key is never
    silently ignored."""
    if not isinstance(data, Mapping):
        raise MesostructureError(f"mesostructure file {path}: expected a table of keys ({', '.join(FILE_KEYS)})")
    for key in data:
        if key not in FILE_KEYS:
            raise MesostructureError(unknown_key_message(key, "at the top level", path, FILE_KEYS))
    grains = data.get("grains")
    for label, grain in enumerate(grains if isinstance(grains, list) else [], start=1):
        if not isinstance(grain, Mapping):
            raise MesostructureError(f"mesostructure file {path}: grain {label} is not a table of "
                                     f"{', '.join(GRAIN_KEYS)}")
        for key in grain:
            if key not in GRAIN_KEYS:
                raise MesostructureError(unknown_key_message(key, f"in grain {label}",
                                                             path, GRAIN_KEYS))


def _number(value: Any) -> float:
    """A number of a file as a float; TypeError for text, booleans and other values."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{value!r} is not a number")
    return float(value)


def _label(value: Any) -> int:
    """A grain label of a file as an int; TypeError for text, booleans, fractions and other values."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{value!r} is not a grain label (an integer)")
    return value


_OUTER_SHAPES = {2: (None, "a list of grain labels"), 3: (3, "a list of [a, b, c] triangles")}
"""By dimension: labels per face of ``outer`` (None: one polygon) and what the file must give."""


def _outer(value: Any, dim: int) -> np.ndarray:
    """The ``outer`` of a file (``_OUTER_SHAPES``); TypeError for another shape."""
    corners, what = _OUTER_SHAPES[dim]
    rows = [value] if corners is None else value
    if not isinstance(value, list) or not all(isinstance(row, list) and corners in (None, len(row)) for row in rows):
        raise TypeError(f"outer must be {what}")
    labels = np.asarray([[_label(v) for v in row] for row in rows], dtype=np.int64)
    return labels.reshape(-1) if corners is None else labels.reshape(-1, corners)


def _from_mapping(data: Mapping[str, Any], *, default_name: str, contact_tolerance: float) -> Mesostructure:
    name = str(data.get("name", default_name))
    try:
        grains = data["grains"]
        radius = [_number(g["radius"]) for g in grains]
        position = [[_number(v) for v in g["position"]] for g in grains]
        driven = [list(g["driven"]) for g in grains]
        axes = AXIS_NAMES.get(len(position[0]) if position else 2, AXIS_NAMES[2])
        if not all(isinstance(v, bool) and len(d) == len(axes) for d in driven for v in d):
            raise MesostructureError(f"mesostructure {name!r}: each grain needs driven = "
                                     f"[{', '.join(['bool'] * len(axes))}] ({', '.join(axes)})")
        to_index = lambda labels: [[_label(a) - 1 for a in p] for p in labels]  # noqa: E731
        pairs = data.get("pairs")
        pairs = list(combinations(range(len(radius)), 2)) if pairs is None else [tuple(sorted(p)) for p in to_index(pairs)]
        meso = Mesostructure(name=name, radius=np.asarray(radius, float), position=np.asarray(position, float),
                             driven=np.asarray(driven), pairs=np.asarray(pairs, dtype=np.int64).reshape(-1, 2),
                             outer=_outer(data["outer"], len(axes)) - 1,
                             cell_size=np.asarray([_number(v) for v in data["cell_size"]], float),
                             pair_label=hcell.file_labels(name, pairs, data), contact_tolerance=contact_tolerance)
        return _with_kinematics(with_declarations(meso), data.get("kinematics"), f"mesostructure {name!r}")
    except KeyError as exc:
        raise MesostructureError(f"mesostructure {name!r}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, MesostructureError):
            raise
        raise MesostructureError(f"mesostructure {name!r}: malformed entry ({exc})") from None


DESCRIPTION_FIELDS = {"radius": "radius", "position": "position", "driven": "driven", "pairs": "pairs", "outer": "outer",
                      "cell_size": "cell_size", LABEL_KEY: "pair_label"}
"""Key -> Mesostructure field of the arrays of a JSON description (with ``name``, ``contact_tolerance``)."""


def describe(meso: Mesostructure) -> str:
    """Canonical JSON text of ``meso``: enough to rebuild it with ``from_description``.

    Canonical: keys sorted, no whitespace (``json.dumps(sort_keys=True, separators=(",", ":"))``),
    floats written by ``repr`` (exact round trip), indices 0-based. Equal cells give equal text.
    """
    data: dict[str, Any] = {"format": "meso-hmodel-mesostructure", "version": 1, "name": meso.name,
                            "contact_tolerance": float(meso.contact_tolerance)}
    for key, name in DESCRIPTION_FIELDS.items():
        data[key] = np.asarray(getattr(meso, name)).tolist()
    gain = meso.parameters.get(hcell.AXISYMMETRIC_KINEMATICS, 0.0)
    if gain:  # only then: descriptions of other cells keep their text
        data["kinematics"] = "amplified" if gain == hcell.KINEMATICS_GAIN["amplified"] else "axisymmetric"
    return json.dumps(data, sort_keys=True, separators=(",", ":"))


def from_description(text: str) -> Mesostructure:
    """Inverse of ``describe`` (the labels declare the observables and parameters, ``with_declarations``).

    Raises:
        MesostructureError: not a mesostructure description, or an invalid cell (one line).
    """
    try:
        data = json.loads(text)
    except (TypeError, json.JSONDecodeError) as exc:
        raise MesostructureError(f"mesostructure description is not JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != "meso-hmodel-mesostructure":
        raise MesostructureError("text is not a mesostructure description (format meso-hmodel-mesostructure)")
    unknown = sorted(set(data) - {"format", "version", "name", "contact_tolerance", "kinematics", *DESCRIPTION_FIELDS})
    if data.get("version") != 1:
        raise MesostructureError(f"mesostructure description of version {data.get('version')!r}: this package reads 1")
    if unknown:
        raise MesostructureError(f"mesostructure description: unknown key {unknown[0]!r}")
    if not all(isinstance(v, bool) for row in data.get("driven", []) for v in (row if isinstance(row, list) else [row])):
        raise MesostructureError("mesostructure description: driven flags must be booleans")
    try:
        return _with_kinematics(with_declarations(Mesostructure(
            name=str(data["name"]), radius=np.asarray(data["radius"], np.float64),
            position=np.asarray(data["position"], np.float64), driven=np.asarray(data["driven"], bool),
            pairs=np.asarray(data["pairs"], np.int64).reshape(-1, 2), outer=np.asarray(data["outer"], np.int64),
            cell_size=np.asarray(data["cell_size"], np.float64), pair_label=np.asarray(data[LABEL_KEY], np.int8),
            contact_tolerance=float(data["contact_tolerance"]))), data.get("kinematics"), "mesostructure description")
    except KeyError as exc:
        raise MesostructureError(f"mesostructure description: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, MesostructureError):
            raise
        raise MesostructureError(f"mesostructure description: malformed entry ({exc})") from None


def description_sha256(text: str) -> str:
    """Hex sha256 of a description text (UTF-8)."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
