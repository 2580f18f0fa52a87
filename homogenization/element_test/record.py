"""What an element test records: ``Record`` (one material point, 2D and 3D) and ``History`` (the buffers
of a run of n material points, filled increment by increment by ``element_test.stages``).

Sign convention: compression and contraction positive; stresses [N/m] (2D) or [Pa] (3D), strains [-].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from homogenization.element_test.programme import Programme
from homogenization.material.density import DensityMap, current_void_ratio, initial_void_ratio
from warp_hcell.core.dimension import dimension


@dataclass
class Record:
    """History of a run, one entry per increment (the force-free initial state is implicit).

    Stresses [N/m] (2D) or [Pa] (3D) and strains [-] are compression/contraction positive;
    strains are the sums of the applied macro increments, counted from the initial state.
    n: increments; m: snapshots; n_cells: cells of the orientation set. The fields of a 3D run
    only are None in 2D.
    """

    stage: np.ndarray
    """Stage label of each increment, shape (n,), str."""
    eps11: np.ndarray
    """Macro strain [-], shape (n,)."""
    eps22: np.ndarray
    """Macro strain [-], shape (n,)."""
    sigma11: np.ndarray
    """Macro stress, shape (n,)."""
    sigma22: np.ndarray
    """Macro stress, shape (n,)."""
    sigma12: np.ndarray
    """Macro shear stress, shape (n,)."""
    p: np.ndarray
    """Mean stress, (sigma11 + sigma22) / 2 in 2D, tr(sigma) / 3 in 3D, shape (n,)."""
    q: np.ndarray
    """Deviator, sigma11 - sigma22 in 2D, sqrt(3 J2) in 3D, shape (n,)."""
    J: np.ndarray
    """Volume ratio V / V0 [-], shape (n,)."""
    volume: np.ndarray
    """Macro volume V = V0 J [m^2] (3D: [m^3]), shape (n,)."""
    newton_iterations: np.ndarray
    """``step`` calls spent on the increment (1 when purely strain-controlled), shape (n,), int."""
    diagnostics: dict[str, np.ndarray]
    """Backend diagnostics of the accepted ``step`` call per increment (e.g. DEM ``substeps``,
    ``n_unconverged``), name -> shape (n,), NaN where absent; ``<name>_all_calls`` sums it over
    every ``step`` call of the increment, stress control's trial calls included."""
    snapshot_increment: np.ndarray
    """Completed increments at each snapshot, shape (m,)."""
    snapshot_stage: np.ndarray
    """Stage label of each snapshot, shape (m,), str."""
    snapshots: dict[str, np.ndarray]
    """Per-cell ``cell_model.observables``, name -> shape (m, n_cells)."""
    theta_deg: np.ndarray
    """Cell-axis orientations [deg] (3D: the angle between each cell axis and axis 1), shape (n_cells,)."""
    weights: np.ndarray
    """Fabric weights [-], shape (n_cells,)."""
    V0: float
    """Initial macro volume [m^2] (3D: [m^3])."""
    parameters: dict[str, float]
    """The mesostructure's named parameters (``Mesostructure.parameters``, e.g. ``alpha0_deg``)."""
    backend: str
    """Name of the cell model."""
    programme: Programme
    """The loading programme that was run."""
    final_state: dict[str, np.ndarray] = field(default_factory=dict)
    """``cell_model.state_to_arrays`` of the last state (resume, inspection)."""
    step_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Wall time of each programme step [s], shape (n_steps,); not written to run files."""
    eps33: np.ndarray | None = None
    """Third normal strain [-] of a 3D run, shape (n,)."""
    sigma33: np.ndarray | None = None
    """Third normal stress of a 3D run, shape (n,)."""
    sigma23: np.ndarray | None = None
    """Shear stress of a 3D run, shape (n,)."""
    sigma13: np.ndarray | None = None
    """Shear stress of a 3D run, shape (n,)."""
    frames: np.ndarray | None = None
    """Cell frames (n, t1, t2) as columns [-] of a 3D run, shape (n_cells, 3, 3)."""
    e0: float | None = None
    """Void ratio [-] given for the initial (force-free) cells (``material.density``); None: not given."""
    density_map: DensityMap | None = None
    """The void-ratio map the cells' alpha0 was read from where ``e0`` is given."""

    @property
    def n_increments(self) -> int:
        """Number of recorded increments."""
        return int(self.eps11.shape[0])

    @property
    def dim(self) -> int:
        """2 for a plane-strain run, 3 for a triaxial one."""
        return 2 if self.eps33 is None else 3

    @property
    def initial_void_ratio(self) -> float:
        """e0 [-]: as given, else the default map's at the cell's alpha0 (``density.initial_void_ratio``;
        NaN outside the map or for a cell without alpha0)."""
        if self.e0 is not None:
            return float(self.e0)
        return initial_void_ratio(self.parameters.get("alpha0_deg"), self.dim)

    @property
    def e(self) -> np.ndarray:
        """Current void ratio (1 + e0) J - 1 [-] (``initial_void_ratio``), shape (n,); NaN where e0 is not known."""
        return current_void_ratio(self.initial_void_ratio, self.J)

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
