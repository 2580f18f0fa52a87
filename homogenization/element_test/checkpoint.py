"""Checkpoints of an element test, so that a killed run resumes where it stopped with the same result.

``RunCheckpoint(path, key, seconds)`` is handed to ``driver.run``: after a recorded increment, once
``seconds`` of wall time have passed since the last save (0: after every increment; after the last
increment also where ``keep_last``), the run's whole state is written to ``path`` (HDF5, atomically: a kill during the write leaves
the previous checkpoint): the material points' state (the cells' ``state_to_arrays``, J, strain, stress,
the largest stress so far), the stage and increment reached with the stage's solver state
(``stages.StageState``), the recorded history (``record.History``), the jumps taken, the wall time so far,
and the run-time state of the cell model's out-of-distribution monitor and of the renewal rule. A run
given a checkpoint that exists starts from it and repeats the uninterrupted run's arithmetic, so its
``Record`` is the same bit for bit; one written after the last increment gives the record without a step.
``key`` (JSON-able) is stored; ``check`` refuses a checkpoint written with another key.

Runs with a renewal rule other than the critical-state one (``critical_state.Renewal``: e.g. a posterior's
interlocking friction, which changes the cell model's laws) and runs with ``before_stage`` actions are not
checkpointed (``supports`` says why).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from homogenization.element_test.points import MaterialPoints
from homogenization.element_test.record import History
from homogenization.element_test.solver import StressControl
from homogenization.element_test.stages import StageState
from homogenization.material.critical_state import Renewal
from homogenization.material.homogenised import MaterialState
from warp_hcell.core.errors import UserError
from warp_hcell.core.files import atomic_write, stored_settings_differ

FORMAT = "hmodel-element-test-checkpoint/1"
_LOGS = ("log",)
"""List attributes of a renewal rule: one tuple of per-point arrays per recorded increment."""


def supports(points: MaterialPoints, before_stage: Any) -> str | None:
    """None where a run of ``points`` can be checkpointed; else why not (one phrase)."""
    if before_stage:
        return "actions between its stages (e.g. an erosion) keep no checkpoint"
    if points.renewal is not None and type(points.renewal) is not Renewal:
        return f"its rule {type(points.renewal).__name__} changes the cells' laws and keeps no checkpoint"
    return None


def _object_state(obj: Any) -> dict[str, np.ndarray]:
    """The array and number attributes of ``obj`` (its run-time state), and its ``_LOGS`` lists stacked
    (shape (increments, entries, n_points))."""
    out: dict[str, np.ndarray] = {}
    for name, value in vars(obj).items():
        if isinstance(value, (np.ndarray, bool, int, float, np.number, np.bool_)):
            out[name] = np.asarray(value)
        elif name in _LOGS:
            out[f"{name}.stacked"] = (np.array([np.stack(entry) for entry in value]) if value
                                      else np.zeros((0, 0, 0), dtype=np.int64))
    return out


def _restore_object(obj: Any, arrays: Mapping[str, np.ndarray]) -> None:
    """Set the attributes of ``obj`` that ``_object_state`` saved (numbers as Python numbers)."""
    for name, value in arrays.items():
        if name.endswith(".stacked"):
            setattr(obj, name.removesuffix(".stacked"), [tuple(np.array(row) for row in entry) for entry in value])
        elif value.ndim == 0 and isinstance(getattr(obj, name, None), (bool, int, float, np.generic)):
            setattr(obj, name, type(getattr(obj, name))(value[()]))
        else:
            setattr(obj, name, np.array(value))


def _monitor(points: MaterialPoints) -> Any:
    """The cell model's out-of-distribution monitor (``homogenization.ann.ood.OodMonitor``), None without one."""
    return getattr(points.model, "ood_monitor", None)


_STEP_PROVENANCE = ("step_path", "precompiled_reason", "precompiled_loader")
"""Which code ran the ANN's fused step (``training.inference``): set by its first step, so kept for a run resumed
from its last increment, which takes none."""


def _step_provenance(points: MaterialPoints) -> dict[str, Any]:
    fast = getattr(points.model, "fast", None)
    return {} if fast is None or fast.step_path is None else {k: getattr(fast, k) for k in _STEP_PROVENANCE}


class RunCheckpoint:
    """Where and how often an element test saves itself (module docstring).

    Args:
        path: the checkpoint file (HDF5).
        key: the run's settings (JSON-able); a checkpoint written with another key is refused.
        seconds: wall time [s] between two saves, >= 0 (0: after every increment).
    """

    def __init__(self, path: Path, key: Mapping[str, Any], seconds: float) -> None:
        if not float(seconds) >= 0.0:
            raise ValueError(f"checkpoint interval {seconds} s must be >= 0")
        self.path, self.seconds = Path(path), float(seconds)
        self.key = json.dumps(dict(key), sort_keys=True, default=str)
        self.keep_last = False
        """Also save after the last increment when not due (a backend that other backends of the command follow)."""
        self._last = time.monotonic()

    def exists(self) -> bool:
        """Whether the checkpoint file is there."""
        return self.path.is_file()

    def check(self) -> None:
        """UserError (one line) unless the checkpoint is readable and was written with this key."""
        differ = stored_settings_differ(self.path, FORMAT, "key", self.key)
        if differ:
            raise UserError(f"checkpoint {self.path} was written with other settings ({', '.join(differ[:6])}"
                            f"{', ...' if len(differ) > 6 else ''})")

    def progress(self) -> tuple[int, int]:
        """(increments recorded, stages finished) that the checkpoint holds."""
        with h5py.File(self.path, "r") as f:
            return int(f.attrs["k"]), int(f.attrs["stage"])

    def due(self) -> bool:
        """Whether ``seconds`` have passed since the last save (or since this object was made)."""
        return time.monotonic() - self._last >= self.seconds

    def save(self, solver: StressControl, history: History, stage: int, stage_stress: np.ndarray,
             at: StageState | None, seconds: np.ndarray) -> None:
        """Write the run's state: ``stage`` (index of the stage under way, or the number of stages after the last),
        the stresses ``stage_stress`` (n, n_voigt) its plan started from, ``at`` where it is (None after the
        last), the wall time ``seconds`` of every stage so far."""
        points, k = solver.points, history.k
        with atomic_write(self.path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs.update(format=FORMAT, key=self.key, k=k, stage=stage,
                           step_provenance=json.dumps(_step_provenance(points)))
            _put(f.create_group("cells"), points.model.state_to_arrays(points.state.cells))
            _put(f.create_group("points"), {
                "J": points.state.J, "strain": points.state.strain, "stress": points.state.stress,
                "peak": points.peak, "jumps": solver.jumps, "stage_stress": stage_stress, "seconds": seconds,
                **({} if points.last_trial is None else {"last_trial": points.last_trial})})
            if at is not None:
                _put(f.create_group("stage_state"), {
                    "done": at.done, "d": at.d, "moving": at.moving, "fallback": at.fallback,
                    **({} if at.tangent is None else {"tangent": at.tangent})})
            _put(f.create_group("history"), {
                "rows": history.rows[:k], "iterations": history.iterations[:k],
                "stage_index": history.stage_index[:k], "snap_k": np.array(history.snap_k, dtype=np.int64),
                "snap_stage": np.array(history.snap_stage, dtype=np.int64)})
            _put(f.create_group("diagnostics"), {name: v[:k] for name, v in history.diagnostics.items()})
            snaps = f.create_group("snaps")
            for j, snap in enumerate(history.snaps):
                _put(snaps.create_group(str(j)), snap)
            if points.renewal is not None:
                _put(f.create_group("renewal"), _object_state(points.renewal))
            if _monitor(points) is not None:
                _put(f.create_group("monitor"), _object_state(_monitor(points)))
        self._last = time.monotonic()

    def load(self, solver: StressControl, history: History) -> tuple[int, np.ndarray, StageState | None, np.ndarray]:
        """Put the saved state into ``solver.points``, ``solver`` and ``history`` (made as for a new run); returns
        (stage, the stresses its plan started from, where it is (None: the run had ended), the stages' wall time)."""
        points = solver.points
        with h5py.File(self.path, "r") as f:
            k, stage = int(f.attrs["k"]), int(f.attrs["stage"])
            p = _get(f["points"])
            cells = points.model.state_from_arrays(_get(f["cells"]))
            points.state = MaterialState(cells, p["J"], p["strain"], p["stress"])
            points.peak, solver.jumps = p["peak"], p["jumps"]
            points.last_trial = p.get("last_trial")
            at = None
            if "stage_state" in f:
                s = _get(f["stage_state"])
                at = StageState(int(s["done"]), s["d"], s.get("tangent"), s["moving"], s["fallback"])
            h = _get(f["history"])
            history.rows[:k], history.iterations[:k], history.stage_index[:k] = h["rows"], h["iterations"], \
                h["stage_index"]
            history.k, history.snap_k, history.snap_stage = k, [int(v) for v in h["snap_k"]], \
                [int(v) for v in h["snap_stage"]]
            for name, value in _get(f["diagnostics"]).items():
                history.diagnostics[name] = np.full(history.rows.shape[0], np.nan)
                history.diagnostics[name][:k] = value
            history.snaps = [_get(f["snaps"][str(j)]) for j in range(len(f["snaps"]))]
            if "renewal" in f:
                _restore_object(points.renewal, _get(f["renewal"]))
            if "monitor" in f:
                _restore_object(_monitor(points), _get(f["monitor"]))
                _monitor(points).resumed()  # its warning, which the interrupted process said
            for name, value in json.loads(f.attrs["step_provenance"]).items():
                setattr(points.model.fast, name, value)  # a step of this process sets them again
        self._last = time.monotonic()
        return stage, p["stage_stress"], at, p["seconds"]


def _put(group: h5py.Group, arrays: Mapping[str, Any]) -> None:
    """Each array of ``arrays`` as a dataset of ``group``; their order kept in the attribute ``names``."""
    for name, value in arrays.items():
        group[name] = np.asarray(value)
    group.attrs["names"] = json.dumps(list(arrays))


def _get(group: h5py.Group) -> dict[str, Any]:
    """The arrays that ``_put`` wrote, in their order (0-d ones as numpy scalars)."""
    return {name: group[name][()] for name in json.loads(group.attrs["names"])}
