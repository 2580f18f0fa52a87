"""What an element test records: ``Record`` (one material point, 2D and 3D) and ``History`` (the buffers
of a run of n material points, filled increment by increment by ``element_test.stages``).

Sign convention: compression and contraction positive; stresses [N/m] (2D) or [Pa] (3D), strains [-].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from homogenization.element_test.programme import Programme
from warp_hcell.core.dimension import dimension


@dataclass
class Record:
    """History of a run, one entry per increment (the force-free initial state is implicit).

    Stresses [N/m] and strains [-] are compression/contraction positive; strains are the
    sums of the applied macro increments, counted from the initial state.

    Attributes:
        stage: stage label of each increment, shape (n,), str.
        eps11, eps22: macro strain [-], shape (n,).
        sigma11, sigma22, sigma12: macro stress [N/m], shape (n,).
        p: mean stress (sigma11 + sigma22) / 2 [N/m], shape (n,).
        q: deviator sigma11 - sigma22 [N/m], shape (n,).
        J: volume ratio V / V0 [-], shape (n,).
        volume: macro volume V = V0 J [m^2], shape (n,).
        newton_iterations: ``step`` calls spent on the increment (1 when purely
            strain-controlled), shape (n,), int.
        diagnostics: backend diagnostics of the accepted ``step`` call per increment (e.g.
            DEM ``substeps``, ``n_unconverged``), name -> shape (n,); NaN where absent.
            ``<name>_all_calls`` sums the same diagnostic over every ``step`` call of the
            increment, trial calls of stress control included (the work really spent).
        snapshot_increment: number of completed increments at each snapshot, shape (m,).
        snapshot_stage: stage label of each snapshot, shape (m,), str.
        snapshots: per-cell ``cell_model.observables``, name -> shape (m, n_cells).
        theta_deg: cell-axis orientations [deg], shape (n_cells,).
        weights: fabric weights [-], shape (n_cells,).
        V0: initial macro volume [m^2] (3D: [m^3]).
        parameters: the named parameters of the mesostructure (``Mesostructure.parameters``,
            e.g. ``alpha0_deg`` [deg]), copied without knowing what they are.
        backend: name of the cell model.
        programme: the loading programme that was run.
        final_state: ``cell_model.state_to_arrays`` of the last state (resume, inspection).
        step_seconds: wall time of each programme step [s], shape (n_steps,); not written
            to run files, which stay bit-reproducible.
        eps33, sigma33, sigma23, sigma13: the third normal strain and the stress components of a
            3D run (None in 2D), shape (n,); there p = tr(sigma) / 3 and q = sqrt(3 J2) [Pa],
            sigma12 the 12 shear stress, and theta_deg the angle between each cell axis and axis 1.
        frames: 3D cell frames (n, t1, t2) as columns [-], shape (n_cells, 3, 3); None in 2D.
    """

    stage: np.ndarray
    eps11: np.ndarray
    eps22: np.ndarray
    sigma11: np.ndarray
    sigma22: np.ndarray
    sigma12: np.ndarray
    p: np.ndarray
    q: np.ndarray
    J: np.ndarray
    volume: np.ndarray
    newton_iterations: np.ndarray
    diagnostics: dict[str, np.ndarray]
    snapshot_increment: np.ndarray
    snapshot_stage: np.ndarray
    snapshots: dict[str, np.ndarray]
    theta_deg: np.ndarray
    weights: np.ndarray
    V0: float
    parameters: dict[str, float]
    backend: str
    programme: Programme
    final_state: dict[str, np.ndarray] = field(default_factory=dict)
    step_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))
    eps33: np.ndarray | None = None
    sigma33: np.ndarray | None = None
    sigma23: np.ndarray | None = None
    sigma13: np.ndarray | None = None
    frames: np.ndarray | None = None

    @property
    def n_increments(self) -> int:
        """Number of recorded increments."""
        return int(self.eps11.shape[0])

    @property
    def dim(self) -> int:
        """2 for a plane-strain run, 3 for a triaxial one."""
        return 2 if self.eps33 is None else 3

    @property
    def eps_v(self) -> np.ndarray:
        """Volumetric strain eps11 + eps22 (3D: + eps33) [-], contraction positive, shape (n,)."""
        normal = self.eps11 + self.eps22
        return normal if self.eps33 is None else normal + self.eps33


class History:
    """Buffers of a run of n material points, one row per increment (``element_test.stages``).

    Args:
        n_max: most increments the run can take.
        n_points: material points of the run.
        dim: normal components controlled (2 or 3); the stress has 3 (2D) or 6 (3D) components.
        observe: also keep per-cell observables at snapshots (``snapshot``).

    Attributes:
        rows: per increment and point, the macro strain (dim components) [-], the stress (3 or 6) [N/m or
            Pa] and J [-], shape (n_max, n_points, dim + n_stress + 1); the first ``k`` are filled.
        iterations: ``step`` calls spent on each increment, shape (n_max,).
        stage_index: programme step of each increment, shape (n_max,).
        diagnostics: backend diagnostics of the accepted call (``<name>_all_calls``: summed over every call
            of the increment; ``stress_control_jump``), name -> shape (n_max,), NaN where absent.
        snap_k, snap_stage, snaps: increments, stages and per-cell observables of the snapshots.
    """

    def __init__(self, n_max: int, n_points: int, dim: int, *, observe: bool = True) -> None:
        n_stress = dimension(dim).n_voigt
        self.dim = dim
        self.rows = np.empty((n_max, n_points, dim + n_stress + 1))
        self.iterations = np.empty(n_max, dtype=np.int64)
        self.stage_index = np.empty(n_max, dtype=np.int64)
        self.diagnostics: dict[str, np.ndarray] = {}
        self.observe = observe
        self.k = 0
        self.snap_k: list[int] = []
        self.snap_stage: list[int] = []
        self.snaps: list[dict[str, np.ndarray]] = []

    def record(self, points: Any, calls: int, stage: int, jump: np.ndarray | None) -> None:
        """Append the state of ``points`` (``element_test.points.MaterialPoints``) after an increment that cost
        ``calls`` step calls; ``jump``: per point whether stress control took the nearer side of a response jump
        (None where no stress was controlled). Resets the points' per-increment call totals."""
        k = self.k
        state = points.state
        row = self.rows[k]
        row[:, :self.dim] = state.strain[:, :self.dim]
        row[:, self.dim:-1] = state.stress
        row[:, -1] = state.J
        self.iterations[k] = calls
        self.stage_index[k] = stage
        for name, value in points.accepted_diagnostics.items():
            self._diagnostic(name, k, value)
        for name, value in points.call_totals.items():
            self._diagnostic(f"{name}_all_calls", k, value)
        if jump is not None:
            self._diagnostic("stress_control_jump", k, float(np.any(jump)))
        points.call_totals = {}
        self.k = k + 1

    def _diagnostic(self, name: str, k: int, value: float) -> None:
        if name not in self.diagnostics:
            self.diagnostics[name] = np.full(self.rows.shape[0], np.nan)
        self.diagnostics[name][k] = value

    def snapshot(self, points: Any, stage: int) -> None:
        """Keep the per-cell observables of ``points`` now (once per increment; nothing unless ``observe``)."""
        if not self.observe or (self.snap_k and self.snap_k[-1] == self.k):
            return
        self.snap_k.append(self.k)
        self.snap_stage.append(stage)
        self.snaps.append({name: np.array(v) for name, v in points.model.observables(points.state.cells).items()})
