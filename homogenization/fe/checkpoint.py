"""Checkpoints of a boundary-value run, so that a killed run resumes with the same result.

``Checkpoint(path, every, parameters)`` is handed to ``BiaxialSpecimen.run``: after every
``every`` converged load steps (and after the last) the run's whole state is written to ``path``
(HDF5, atomically: a kill during the write leaves the previous checkpoint): the unknowns of the
last two steps, the material state (J, strain, stress and the backend's cell state through
``state_to_arrays``) and every ``StepResult`` so far. A run given a checkpoint that exists
starts from it: ``load`` rebuilds the same arrays bit for bit, so the resumed run repeats the
uninterrupted one's arithmetic. ``parameters`` (a JSON-able mapping) is stored, and ``check``
refuses a checkpoint written with other parameters.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from homogenization.fe.solver import StepResult
from homogenization.material.homogenised import HomogenisedMaterial, MaterialState
from warp_hcell.core.errors import UserError
from warp_hcell.core.files import atomic_write, stored_settings_differ

FORMAT = "hmodel-bvp-checkpoint/1"
_ARRAYS = ("displacement", "strain", "stress", "opening", "open_fraction")
_SCALARS = ("eps11", "eps22", "sigma11", "sigma22", "sigma12")


class Checkpoint:
    """Where and how often a run saves itself (module docstring).

    Args:
        path: the checkpoint file (HDF5).
        every: save after every ``every`` converged load steps, >= 1.
        parameters: the run's parameters (JSON-able); a checkpoint with others is refused.
    """

    def __init__(self, path: Path, every: int, parameters: Mapping[str, Any]) -> None:
        if int(every) < 1:
            raise ValueError(f"checkpoint interval {every} must be >= 1")
        self.path, self.every = Path(path), int(every)
        self.parameters = json.dumps(dict(parameters), sort_keys=True)

    def exists(self) -> bool:
        """Whether the checkpoint file is there."""
        return self.path.is_file()

    def steps_done(self) -> int:
        """Converged load steps the checkpoint holds."""
        with h5py.File(self.path, "r") as f:
            return int(f.attrs["steps_done"])

    def check(self) -> None:
        """UserError (one line) unless the checkpoint is readable and was written with these parameters."""
        differ = stored_settings_differ(self.path, FORMAT, "parameters", self.parameters)
        if differ:
            raise UserError(f"checkpoint {self.path} was written with other settings ({', '.join(differ)}); "
                            f"resume with the same flags")

    def save(self, x: np.ndarray, previous: np.ndarray, material: HomogenisedMaterial, state: MaterialState,
             results: list[StepResult]) -> None:
        """Write the run's state after ``len(results)`` steps (atomically)."""
        width = max(len(r.residuals) for r in results)
        residuals = np.full((len(results), width), np.nan)
        for k, r in enumerate(results):
            residuals[k, :len(r.residuals)] = r.residuals
        with atomic_write(self.path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["parameters"] = self.parameters
            f.attrs["steps_done"] = len(results)
            f["x"], f["previous"] = x, previous
            f["J"], f["strain"], f["stress"] = state.J, state.strain, state.stress
            cells = f.create_group("cells")
            for name, value in material.model.state_to_arrays(state.cells).items():
                cells[name] = np.asarray(value)
            res = f.create_group("results")
            res["stage"] = np.array([r.stage for r in results], dtype=h5py.string_dtype())
            for name in _SCALARS:
                res[name] = np.array([getattr(r, name) for r in results])
            res["iterations"] = np.array([r.iterations for r in results])
            res["residual_counts"] = np.array([len(r.residuals) for r in results])
            res["residuals"] = residuals
            res["diagnostics"] = np.array([json.dumps(r.diagnostics) for r in results], dtype=h5py.string_dtype())
            for name in _ARRAYS:
                res[name] = np.stack([getattr(r, name) for r in results])

    def load(self, material: HomogenisedMaterial, n_steps: int) -> tuple[np.ndarray, np.ndarray, MaterialState,
                                                                         list[StepResult]]:
        """(x, previous, material state, results) saved; ``material.init_state()`` must have run (V0).

        Raises:
            UserError: the checkpoint holds more steps than the programme's ``n_steps``.
        """
        with h5py.File(self.path, "r") as f:
            done = int(f.attrs["steps_done"])
            if done > n_steps:
                raise UserError(f"checkpoint {self.path} holds {done} steps, the programme has {n_steps}")
            x, previous = f["x"][()], f["previous"][()]
            cells = material.model.state_from_arrays({name: f["cells"][name][()] for name in f["cells"]})
            state = MaterialState(cells, f["J"][()], f["strain"][()], f["stress"][()])
            res = f["results"]
            stage = res["stage"].asstr()[()]
            columns = {name: res[name][()] for name in (*_SCALARS, *_ARRAYS, "iterations", "residual_counts",
                                                        "residuals")}
            diagnostics = [json.loads(text) for text in res["diagnostics"].asstr()[()]]
        results = [StepResult(str(stage[k]), *(float(columns[name][k]) for name in _SCALARS),
                              int(columns["iterations"][k]),
                              [float(v) for v in columns["residuals"][k, :columns["residual_counts"][k]]],
                              columns["displacement"][k], columns["strain"][k], columns["stress"][k], diagnostics[k],
                              columns["opening"][k], columns["open_fraction"][k])
                   for k in range(done)]
        return x, previous, state, results
