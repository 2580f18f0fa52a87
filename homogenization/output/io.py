"""Run files: ``DIR/run.h5`` (everything) and ``DIR/curve.csv`` (the macro curve).

``write_run(directory, record, ...)`` writes both through ``files.atomic_write`` so that a
failed run never destroys older output; ``read_run(path)`` reads ``run.h5`` back into a
``driver.Record`` and raises ``cli.UserError`` (one line) for missing or corrupt files.

run.h5 layout (one dataset per quantity, attributes ``units``, ``description`` and, for
stresses and strains, ``sign_convention``):

- ``/history/{stage, eps11, eps22, sigma11, sigma22, sigma12, p, q, J, volume,
  newton_iterations}``, shape (n_increments,);
- ``/diagnostics/<name>``: backend diagnostics per increment;
- ``/orientations/{theta_deg, weights}``, shape (n_cells,);
- ``/snapshots/{increment, stage}`` (n_snapshots,) and ``/snapshots/cells/<name>``
  (n_snapshots, n_cells): per-cell observables;
- ``/final_state/<name>``: the backend state after the last increment;
- root attributes: backend, the mesostructure's parameters (``cell_parameters`` lists their
  names, e.g. alpha0_deg), V0, the volume rule, the sign convention, the
  programme and the parameters (JSON: with the DEM settings and threads, the ANN model's
  path and sha256 where those backends ran), the seed, the command line, the package
  version of the installed distribution, git revision and library versions.

curve.csv: header ``stage,eps11,eps22,sigma11,sigma22,sigma12,p,q,e``, one row per increment,
strains [-] and stresses [N/m], compression positive; ``e`` the current void ratio
(1 + e0) J - 1 [-] (``Record.e``: e0 as given, else the default void-ratio map's at the cell's
alpha0; ``nan`` where neither is known).

Void ratio (root attributes): ``void_ratio`` e0 [-] (NaN: not known), ``void_ratio_given`` (True:
given, e.g. --void-ratio; False: the default map's at alpha0, or none) and ``density_map`` (JSON
of ``density.DensityMap.to_dict``: the map e0 came from; null where e0 is not known). Files written before these attributes read back with
e0 not given.

Triaxial runs (3D cells, ``Record.dim`` 3): ``/history`` also holds ``eps33, sigma33, sigma23,
sigma13`` (stresses in Pa, p = tr(sigma) / 3, q = sqrt(3 J2), volume in m^3), ``/orientations``
also ``frames`` (n_cells, 3, 3) and theta_deg is the angle between each cell axis and axis 1;
the root attributes give the 3D volume rule and units. Their curve.csv has the header
``stage,eps11,eps22,eps33,sigma11,sigma22,sigma33,p,q,e`` (axis 1 axial).

Reproducible bytes: run.h5 holds no time (no HDF5 object timestamps, no wall time or date)
and its objects and attributes are written in a fixed order, so two runs of the same inputs
with the same code give byte-identical files. The one root attribute that depends on the
invocation rather than on the inputs is ``command``, the command line as typed (it names
the output folder); runs that differ only there differ only in its bytes. The library
versions, ``git_revision`` and, for the dem backend, ``dem_threads`` in ``parameters``
(the machine's default where --threads is not given) describe the code and the machine,
not the run, and are equal on one installation.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from homogenization.element_test import programme as programmes
from warp_hcell.core.errors import UserError
from warp_hcell.core.files import atomic_write
from warp_hcell.core.provenance import provenance
from homogenization.element_test.driver import Record
from homogenization.material.density import DensityMap, default_map
from homogenization.material.orientation import VOLUME_RULE
from homogenization.material.orientation import VOLUME_RULE_3D

RUN_FILE = "run.h5"
CURVE_FILE = "curve.csv"
FORMAT = "hmodel-run/1"
"""Value of the ``format`` root attribute of run files written by this module."""
SIGN_CONVENTION = "compression and contraction positive"
CURVE_COLUMNS = ("stage", "eps11", "eps22", "sigma11", "sigma22", "sigma12", "p", "q", "e")
"""Columns of curve.csv, in order."""

_HISTORY = {
    "eps11": ("1", "macro strain, sum of the applied increments"),
    "eps22": ("1", "macro strain, sum of the applied increments"),
    "sigma11": ("N/m", "macro stress sum_k w_k S_k,11 / V"),
    "sigma22": ("N/m", "macro stress sum_k w_k S_k,22 / V"),
    "sigma12": ("N/m", "macro shear stress sum_k w_k S_k,12 / V"),
    "p": ("N/m", "mean stress (sigma11 + sigma22) / 2"),
    "q": ("N/m", "deviator sigma11 - sigma22"),
    "J": ("1", "volume ratio V / V0"),
    "volume": ("m^2", "macro volume V = V0 J"),
    "newton_iterations": ("1", "cell-model step calls spent on the increment"),
}
_SIGNED = {"eps11", "eps22", "sigma11", "sigma22", "sigma12", "p", "q"}
CURVE_COLUMNS_3D = ("stage", "eps11", "eps22", "eps33", "sigma11", "sigma22", "sigma33", "p", "q", "e")
"""Columns of a 3D run's curve.csv, in order."""
_HISTORY_3D = {
    "eps11": ("1", "macro strain, sum of the applied increments (axis 1 axial)"),
    "eps22": ("1", "macro strain, sum of the applied increments"),
    "eps33": ("1", "macro strain, sum of the applied increments"),
    "sigma11": ("Pa", "macro stress sum_k w_k (R_k S_k R_k^T)_11 / V"),
    "sigma22": ("Pa", "macro stress sum_k w_k (R_k S_k R_k^T)_22 / V"),
    "sigma33": ("Pa", "macro stress sum_k w_k (R_k S_k R_k^T)_33 / V"),
    "sigma23": ("Pa", "macro shear stress sum_k w_k (R_k S_k R_k^T)_23 / V"),
    "sigma13": ("Pa", "macro shear stress sum_k w_k (R_k S_k R_k^T)_13 / V"),
    "sigma12": ("Pa", "macro shear stress sum_k w_k (R_k S_k R_k^T)_12 / V"),
    "p": ("Pa", "mean stress tr(sigma) / 3"),
    "q": ("Pa", "deviator sqrt(3 J2)"),
    "J": ("1", "volume ratio V / V0"),
    "volume": ("m^3", "macro volume V = V0 J"),
    "newton_iterations": ("1", "cell-model step calls spent on the increment"),
}
_SIGNED_3D = _SIGNED | {"eps33", "sigma33", "sigma23", "sigma13"}


@dataclass(frozen=True)
class RunLayout:
    """What the run files of one dimension hold differently (``LAYOUTS[record.dim]``)."""

    history: Mapping[str, tuple[str, str]]
    """The datasets of /history but ``stage``: name -> (units, description)."""
    signed: frozenset[str]
    """The datasets of /history that carry the sign convention."""
    curve_columns: tuple[str, ...]
    """The columns of curve.csv, in order."""
    volume_units: str
    """Units of V0."""
    volume_rule: str
    """How V = V0 J is kept (the orientation set's rule)."""
    stress_units: str
    """Units of the stresses."""
    theta: str
    """Description of /orientations/theta_deg."""
    frames: bool
    """Whether /orientations/frames holds the cell frames R_k (3D)."""


LAYOUTS = {
    2: RunLayout(_HISTORY, frozenset(_SIGNED), CURVE_COLUMNS, "m^2", VOLUME_RULE, "N/m (2D: force per unit length)",
                 "cell-axis angle theta_k = k 180 / N", False),
    3: RunLayout(_HISTORY_3D, frozenset(_SIGNED_3D), CURVE_COLUMNS_3D, "m^3", VOLUME_RULE_3D, "Pa (3D)",
                 "angle between the cell axis n_k and axis 1", True),
}
"""The run-file layout of each dimension."""


@dataclass(frozen=True)
class StoredRun:
    """A run read back from run.h5."""

    record: Record
    """The history, snapshots and final state."""
    attrs: dict[str, Any]
    """Root attributes (provenance, parameters, seed); JSON attributes decoded."""


def _dataset(group: h5py.Group, name: str, data: np.ndarray, units: str, description: str, signed: bool = False) -> None:
    ds = group.create_dataset(name, data=data, track_times=False)
    ds.attrs["units"] = units
    ds.attrs["description"] = description
    if signed:
        ds.attrs["sign_convention"] = SIGN_CONVENTION


def _new_h5(path: Path) -> h5py.File:
    """A new HDF5 file at ``path`` that tracks the creation order of links and attributes and
    stores no object timestamps (h5py before 3.15 gives the root group timestamps with
    ``track_order=True``, so two runs would differ in bytes)."""
    fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
    order = h5py.h5p.CRT_ORDER_TRACKED | h5py.h5p.CRT_ORDER_INDEXED
    fcpl.set_link_creation_order(order)
    fcpl.set_attr_creation_order(order)
    fcpl.set_obj_track_times(False)
    return h5py.File(h5py.h5f.create(os.fsencode(path), h5py.h5f.ACC_TRUNC, fcpl=fcpl))


def _strings(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=object).astype(h5py.string_dtype())


def write_run_h5(path: Path, record: Record, *, parameters: Mapping[str, Any], seed: int,
                 command: str | None = None) -> Path:
    """Write ``record`` to the HDF5 file ``path`` (atomically); returns ``path``.

    Args:
        path: destination file.
        record: the run history from ``driver.run``.
        parameters: the full parameter set of the run (JSON-serialisable).
        seed: the seed of the run.
        command: the command line to record (None: this process's own).
    """
    path = Path(path)
    layout = LAYOUTS[record.dim]
    with atomic_write(path) as tmp, _new_h5(tmp) as f:
        f.attrs["format"] = FORMAT
        f.attrs["backend"] = record.backend
        for name, value in record.parameters.items():
            f.attrs[name] = float(value)
        f.attrs["cell_parameters"] = json.dumps(list(record.parameters))
        f.attrs["V0"] = record.V0
        f.attrs["V0_units"] = layout.volume_units
        f.attrs["volume_rule"] = layout.volume_rule
        f.attrs["sign_convention"] = SIGN_CONVENTION
        f.attrs["stress_units"] = layout.stress_units
        f.attrs["programme"] = json.dumps(programmes.to_dict(record.programme))
        f.attrs["parameters"] = json.dumps(dict(parameters), sort_keys=True)
        f.attrs["seed"] = int(seed)
        f.attrs["void_ratio"] = record.initial_void_ratio
        f.attrs["void_ratio_given"] = record.e0 is not None
        f.attrs["density_map"] = json.dumps(_density_map(record))
        for key, value in provenance(command=command).items():
            f.attrs[key] = value

        hist = f.create_group("history")
        _dataset(hist, "stage", _strings(record.stage), "", "stage label of the increment")
        for name, (units, description) in layout.history.items():
            _dataset(hist, name, getattr(record, name), units, description, name in layout.signed)
        diag = f.create_group("diagnostics")
        for name, values in record.diagnostics.items():
            _dataset(diag, name, values, "", "backend diagnostic of the accepted step call")
        orient = f.create_group("orientations")
        _dataset(orient, "theta_deg", record.theta_deg, "deg", layout.theta)
        _dataset(orient, "weights", record.weights, "1", "fabric weight w_k")
        if layout.frames:
            _dataset(orient, "frames", record.frames, "1", "cell frame R_k, columns (n, t1, t2) in the macro frame")
        snaps = f.create_group("snapshots")
        _dataset(snaps, "increment", record.snapshot_increment, "1", "completed increments at the snapshot")
        _dataset(snaps, "stage", _strings(record.snapshot_stage), "", "stage label at the snapshot")
        cells = snaps.create_group("cells")
        for name, values in record.snapshots.items():
            _dataset(cells, name, values, "see the backend's observables()", "per-cell observable, (n_snapshots, n_cells)")
        state = f.create_group("final_state")
        for name, values in record.final_state.items():
            _dataset(state, name, values, "see the backend's state_to_arrays()", "backend state after the last increment")
    return path


def write_curve_csv(path: Path, record: Record) -> Path:
    """Write the macro curve of ``record`` to ``path`` (atomically); returns ``path``."""
    path = Path(path)
    names = LAYOUTS[record.dim].curve_columns
    columns = np.stack([getattr(record, name) for name in names[1:]], axis=1)  # e: Record.e
    lines = [",".join(names)]
    lines += [f"{stage}," + ",".join(f"{v:.17g}" for v in row) for stage, row in zip(record.stage, columns.tolist())]
    with atomic_write(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def write_run(directory: Path, record: Record, *, parameters: Mapping[str, Any], seed: int,
              command: str | None = None) -> tuple[Path, Path]:
    """Write ``directory/run.h5`` and ``directory/curve.csv``; returns both paths."""
    directory = Path(directory)
    return (write_run_h5(directory / RUN_FILE, record, parameters=parameters, seed=seed, command=command),
            write_curve_csv(directory / CURVE_FILE, record))


def _decode(values: np.ndarray) -> np.ndarray:
    return np.array([v.decode() if isinstance(v, bytes) else str(v) for v in values])


def _cell_parameters(attrs: Mapping[str, Any]) -> dict[str, float]:
    """The mesostructure's parameters of a run file: those ``cell_parameters`` names; a file without
    that list holds the one root attribute ``alpha0_deg`` (NaN for a cell that has none)."""
    if "cell_parameters" in attrs:
        return {name: float(attrs[name]) for name in json.loads(attrs["cell_parameters"])}
    value = float(attrs.get("alpha0_deg", float("nan")))
    return {} if value != value else {"alpha0_deg": value}


def _density_map(record: Record) -> dict[str, float] | None:
    """The map of a run's e0: the given one, else the default map where e0 came from it, else None."""
    if record.density_map is not None:
        return record.density_map.to_dict()
    return default_map(record.dim).to_dict() if math.isfinite(record.initial_void_ratio) else None


def _void_ratio(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """``Record.e0`` and ``density_map`` of a run file: given only where ``void_ratio_given`` (older
    files: not given)."""
    if not attrs.get("void_ratio_given", False):
        return {}
    stored = json.loads(attrs.get("density_map", "null"))
    return {"e0": float(attrs["void_ratio"]), "density_map": None if stored is None else DensityMap.from_dict(stored)}


def read_run(path: Path) -> StoredRun:
    """Read a run file written by ``write_run_h5``; ``path`` may also be a run's folder (its ``run.h5``).

    Raises:
        UserError: one line, if the file is missing (a folder without ``run.h5``: naming the runs in its
            subfolders, or theirs), not HDF5 or not a run file.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / RUN_FILE).is_file():
            inside = sorted(str(run) for run in path.glob(f"*/{RUN_FILE}")) or sorted(
                str(run) for run in path.glob(f"*/*/{RUN_FILE}"))  # a sweep's: DIR/cases/CASE/run.h5
            raise UserError(f"{path}: a folder without {RUN_FILE}"
                            + (f"; the runs in it: {' '.join(inside)}" if inside else ""))
        path = path / RUN_FILE
    if not path.is_file():
        raise UserError(f"{path}: no such run file")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise UserError(f"{path}: not a run file (format attribute is not {FORMAT!r})")
            attrs = {key: (value.item() if isinstance(value, np.generic) else value) for key, value in f.attrs.items()}
            attrs["programme"] = json.loads(attrs["programme"])
            attrs["parameters"] = json.loads(attrs["parameters"])
            hist, snaps = f["history"], f["snapshots"]
            layout = LAYOUTS[3 if "eps33" in hist else 2]
            extra = {"frames": f["orientations/frames"][()]} if layout.frames else {}
            record = Record(
                stage=_decode(hist["stage"][()]),
                **{name: hist[name][()] for name in layout.history},
                **extra,
                diagnostics={name: ds[()] for name, ds in f["diagnostics"].items()},
                snapshot_increment=snaps["increment"][()],
                snapshot_stage=_decode(snaps["stage"][()]),
                snapshots={name: ds[()] for name, ds in snaps["cells"].items()},
                theta_deg=f["orientations/theta_deg"][()],
                weights=f["orientations/weights"][()],
                V0=float(attrs["V0"]),
                parameters=_cell_parameters(attrs),
                backend=str(attrs["backend"]),
                programme=programmes.from_dict(attrs["programme"]),
                final_state={name: ds[()] for name, ds in f["final_state"].items()},
                **_void_ratio(attrs),
            )
    except UserError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise UserError(f"{path}: unreadable or corrupt run file ({reason})") from None
    return StoredRun(record, attrs)
