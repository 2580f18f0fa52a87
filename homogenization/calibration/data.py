"""Measured curves of a calibration: one CSV per test.

Format (units of the package's curve.csv: stresses [N/m] in 2D, [Pa] in 3D, strains [-],
compression and contraction positive)::

    # test = undrained          (or drained: sigma22 held at p0)
    # p0 = 5.85e6               (confining pressure of the isotropic stage [N/m], > 0)
    # void_ratio = 0.72         (optional: the specimen's initial void ratio [-], >= 0)
    eps1,q,p
    0.001,8.1e5,5.7e6
    ...

Tests: ``undrained`` (constant-volume biaxial: d_eps22 = -d_eps11) and ``drained`` (biaxial,
sigma22 = p0), 2D; ``triaxial_undrained`` (isochoric: d_eps22 = d_eps33, volume kept) and
``triaxial_drained`` (sigma22 = sigma33 = p0), 3D, p0 [Pa].

A test that gives its void ratio starts its cells at the alpha0 of the void-ratio map
(``homogenization.material.density``; e_min and e_max calibratable), the others at alpha0.

Comment lines start with ``#``; ``key = value`` comments give the test; other comments are ignored,
whatever their bytes (the other lines are UTF-8). The header names ``eps1`` (axial strain counted
from the end of the isotropic stage, > 0 and increasing) and at least one of ``q`` (sigma11 -
sigma22; 3D: sqrt(3 J2), which is sigma11 - sigma33 where sigma22 = sigma33), ``p`` ((sigma11 +
sigma22) / 2; 3D: tr(sigma) / 3) and ``eps_v`` (eps11 + eps22, 3D: eps11 + eps22 + eps33, from the
end of the isotropic stage). Every value is a finite number; the first p and the largest abs(q) are
within ``UNIT_RATIOS`` of p0 (else a unit mistake, e.g. kPa against Pa).
``read_test`` raises ValueError with one line naming the file and the line for anything else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CHANNELS = ("q", "p", "eps_v")
"""Measured quantities a test may hold: q, p [N/m in 2D, Pa in 3D], eps_v [-]."""
TEST_KINDS = {(2, False): "undrained", (2, True): "drained", (3, False): "triaxial_undrained", (3, True): "triaxial_drained"}
"""(dimension, drained) -> measurement kind: constant-volume or drained biaxial (2D) and triaxial (3D) shear after
isotropic compression."""
TESTS = tuple(TEST_KINDS.values())
"""Measurement kinds (``TEST_KINDS``' values)."""


@dataclass(frozen=True)
class Measurement:
    """One measured curve.

    Attributes:
        name: file name without the folder (labels of outputs).
        path: the CSV file.
        drained: drained (lateral stresses held at p0) rather than constant-volume shear.
        p0: confining pressure [N/m in 2D, Pa in 3D].
        eps1: axial strain [-], shape (n_data,), > 0, increasing.
        observed: channel name -> measured values, shape (n_data,), for the channels of the file.
        dim: 2 (biaxial) or 3 (triaxial).
        void_ratio: the specimen's initial void ratio [-] (``# void_ratio = E``); None: not given.
    """

    name: str
    path: Path
    drained: bool
    p0: float
    eps1: np.ndarray
    observed: dict[str, np.ndarray]
    dim: int = 2
    void_ratio: float | None = None

    @property
    def kind(self) -> str:
        """One of ``TESTS``."""
        return TEST_KINDS[(self.dim, bool(self.drained))]


def read_test(path: Path) -> Measurement:
    """The test of the CSV file ``path`` (format in the module docstring).

    Raises:
        ValueError: one line naming the file (and the line) for a missing, unreadable or malformed file.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: a folder, not a data file (give each test's CSV file with its own --data)")
    if not path.is_file():
        raise ValueError(f"{path}: no such data file")
    try:
        lines = path.read_bytes().removeprefix(b"\xef\xbb\xbf").splitlines()  # UTF-8, byte-order mark or not
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None
    meta: dict[str, str] = {}
    header: list[str] | None = None
    rows: list[list[float]] = []
    numbers: list[int] = []
    for number, raw in enumerate(lines, start=1):
        line = _text(path, number, raw).strip()
        if not line:
            continue
        if line.startswith("#"):
            key, sep, value = line[1:].partition("=")
            if sep and key.strip().lower() in META_KEYS and key.strip().lower() in meta:
                raise ValueError(f"{path}, line {number}: a second '# {key.strip()} = ...' line")
            if sep:
                meta[key.strip().lower()] = value.strip()
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            header = cells
            _check_header(path, number, header)
            continue
        if len(cells) != len(header):
            raise ValueError(f"{path}, line {number}: {len(cells)} values, the header has {len(header)}")
        try:
            if "_" in line:  # float() takes 1_000; a CSV number does not
                raise ValueError
            values = [float(c) for c in cells]
        except ValueError:
            raise ValueError(f"{path}, line {number}: not a number in {line!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{path}, line {number}: values must be finite")
        rows.append(values)
        numbers.append(number)
    if header is None:
        raise ValueError(f"{path}: no header line (eps1 and any of {', '.join(CHANNELS)})")
    if len(rows) < 2:
        raise ValueError(f"{path}: needs at least 2 data rows, has {len(rows)}")
    kind = meta.get("test")
    if kind not in TESTS:
        raise ValueError(f"{path}: give the test in a comment line '# test = undrained' (or {', '.join(TESTS[1:])})"
                         + (f" (got {kind!r})" if kind is not None else ""))
    if "p0" not in meta:
        raise ValueError(f"{path}: give the confining pressure in a comment line '# p0 = 2e5' [N/m in 2D, Pa in 3D]")
    try:
        p0 = float(meta["p0"])
    except ValueError:
        raise ValueError(f"{path}: p0 = {meta['p0']!r} is not a number") from None
    if not (math.isfinite(p0) and p0 > 0.0):
        raise ValueError(f"{path}: p0 = {p0:g} must be finite and > 0")
    void_ratio = None
    if "void_ratio" in meta:
        try:
            void_ratio = float(meta["void_ratio"])
        except ValueError:
            raise ValueError(f"{path}: void_ratio = {meta['void_ratio']!r} is not a number") from None
        if not (math.isfinite(void_ratio) and void_ratio >= 0.0):
            raise ValueError(f"{path}: void_ratio = {void_ratio:g} must be finite and >= 0")
    table = np.array(rows)
    columns = {name: table[:, i].copy() for i, name in enumerate(header)}
    eps1 = columns.pop("eps1")
    bad = np.flatnonzero(np.diff(np.concatenate([[0.0], eps1])) <= 0.0)
    if bad.size:
        raise ValueError(f"{path}, line {numbers[bad[0]]}: eps1 must be > 0 and increasing (counted from the end of "
                         f"the isotropic stage)")
    if eps1[-1] >= 0.5:
        raise ValueError(f"{path}: eps1 reaches {eps1[-1]:g}; strains are fractions, not percent")
    if "eps_v" in columns and np.max(np.abs(columns["eps_v"])) >= 0.5:
        raise ValueError(f"{path}: eps_v reaches {np.max(np.abs(columns['eps_v'])):g}; strains are fractions, not "
                         f"percent")
    flat = [name for name, values in columns.items() if not np.any(values != 0.0)]
    if flat:
        raise ValueError(f"{path}: column {flat[0]} is 0 throughout, so it sets no scale for its misfit (the "
                         f"likelihood's sigma is a fraction of each column's largest value); drop it")
    dim, drained = next(key for key, name in TEST_KINDS.items() if name == kind)
    _check_units(path, p0, columns, numbers, dim)
    return Measurement(path.name, path, drained, p0, eps1, columns, dim, void_ratio)


STRESS_UNITS = {2: "N/m", 3: "Pa"}
"""The stresses' unit by the data's dimension."""
UNIT_RATIOS = {"p": (1.0 / 30.0, 30.0), "q": (0.01, 300.0)}
"""Bounds [-] of the first p, and of the largest abs(q), over p0: outside, the file mixes units (e.g. kPa and Pa) and
is refused. p starts at p0; on real curves the largest q/p0 lies between about 0.1 (loose, undrained) and 30."""


def _check_units(path: Path, p0: float, columns: dict[str, np.ndarray], numbers: list[int], dim: int) -> None:
    """ValueError (one line naming the line) where a stress is outside ``UNIT_RATIOS`` of p0."""
    for name, (low, high) in UNIT_RATIOS.items():
        if name not in columns:
            continue
        row = 0 if name == "p" else int(np.argmax(np.abs(columns[name])))
        value = float(columns[name][row])
        ratio = abs(value) / p0 if name == "q" else value / p0
        if low <= ratio <= high:
            continue
        hint = ("compression is positive" if ratio <= 0.0 else "a unit mistake (stresses in " +
                ("kPa and p0 in Pa?)" if ratio < 1.0 else "Pa and p0 in kPa?)"))
        raise ValueError(f"{path}, line {numbers[row]}: {name} = {value:g} is {ratio:.3g} x p0 = {p0:g}, outside "
                         f"[{low:.2g}, {high:g}] x p0: {hint}; give both in {STRESS_UNITS[dim]}")


def _text(path: Path, number: int, line: bytes) -> str:
    """The line ``number`` of ``path`` as text: a comment's bytes that are not UTF-8 (a lab's Latin-1 note)
    are replaced, as the comment is ignored (a key's value is then not a number, refused); ValueError (one line,
    the byte's column counted in the line as written) for those of any other line."""
    if line.lstrip().startswith(b"#"):
        return line.decode("utf-8", errors="replace")
    try:
        return line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}, line {number}: not UTF-8 text (byte 0x{line[exc.start]:02x} at column "
                         f"{exc.start + 1}); save the file as UTF-8") from None


META_KEYS = ("test", "p0", "void_ratio")
"""The comment lines' keys the reader takes (each once; other ``# key = value`` lines are comments)."""


def _check_header(path: Path, number: int, header: list[str]) -> None:
    if "eps1" not in header:
        raise ValueError(f"{path}, line {number}: the header needs an eps1 column, got {','.join(header)}")
    unknown = [name for name in header if name != "eps1" and name not in CHANNELS]
    if unknown:
        raise ValueError(f"{path}, line {number}: unknown column {unknown[0]!r}; columns are eps1 and any of "
                         f"{', '.join(CHANNELS)}")
    if len(set(header)) != len(header):
        raise ValueError(f"{path}, line {number}: a column appears twice in the header")
    if len(header) < 2:
        raise ValueError(f"{path}, line {number}: the header needs at least one of {', '.join(CHANNELS)} besides eps1")
