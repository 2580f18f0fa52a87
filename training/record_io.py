"""The mapping of a frozen record dataclass as a JSON file stores it, and back (``training.card.ModelCard``,
``homogenization.ann.records``); torch-free, so the learning loop's records load without it.

A record class names in ``OPTIONAL`` (a ClassVar) the fields written only where they are not None.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping


def record_dict(record: Any) -> dict[str, Any]:
    """The fields of ``record``, those of ``record.OPTIONAL`` left out where None."""
    return {f.name: getattr(record, f.name) for f in dataclasses.fields(record)
            if not (f.name in record.OPTIONAL and getattr(record, f.name) is None)}


def record_keywords(cls: type, values: Mapping[str, Any]) -> dict[str, Any]:
    """The keywords of ``cls`` from mapping ``values``; ValueError (one line) for an unknown or missing key."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown key {unknown[0]!r}")
    missing = sorted(name for name in names - set(values) if name not in cls.OPTIONAL)
    if missing:
        raise ValueError(f"{cls.__name__}: missing key {missing[0]!r}")
    return dict(values)
