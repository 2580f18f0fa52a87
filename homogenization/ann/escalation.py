"""The DEM's own increment for the cells of the meso-ANN hybrid whose free grain the corrections cannot place.

The equilibrium corrections of the hybrid (``training.fast_equilibrium3d``, ``training.equilibrium``)
move the free grains by the contact forces on them. A free grain that moved during an increment and
ends it pressed by nothing carries no force, so the corrections leave it where the network put it or
where their last step ended it (in touch with the one grain that pushed it, or just clear of it: a
mechanism, balanced anywhere its pairs do not overlap). The DEM moves such a grain only as far as its
neighbours push it: it ends where the last contact lets it go, in the direction the contact forces
drove it. "Pressed by nothing" is read at the resolution of the corrections' balance, which stops at a
force ratio R: each pair of the grain carries a normal force of at most R times the cell's largest. Where the network's guess
overshoots or turns that motion (a fine grain pushed off a lateral sphere, then sliding along it), the
difference accumulates over the increments and decides when the grain engages or leaves its wedge,
which the homogenised stress shows as a drop at another strain (docs/ann.md, "Released grains").

``DemEscalation.released`` finds those cell-increments (``n_released``); on CPU the hybrid takes them again
with the released grain starting the corrections at rest (``AnnCell._held_at_rest``): a grain nothing pushes
stays, as in the DEM, one a neighbour pushes moves as far as the balance needs. Under ``RELEASE_RULE`` the
grains that nothing presses at the start of the increment (``DemEscalation.resting_dofs``, ``n_resting``) start
the corrections at rest at once, and only a cell whose other grains end released is balanced again; under
``RELEASE_RULE_DRAG`` a grain that started at rest and ends released (pushed lightly: moved by the balance along the
contact normal only) is then relaxed as the DEM relaxes it from rest, the friction of its contacts included
(``DemEscalation.relaxed``, ``homogenization.ann.relaxation``). ``DemEscalation.advance``,
the DEM's increment from the cell's learning state at rest (``warp_hcell.database.probing.step_from_rest``),
replaces them on other devices and serves the sliding cells; the ANN backend counts it in ``n_escalated``.

A grain free along every axis that slides on a contact can also end anywhere along a direction its
contacts leave free, each point an equilibrium of the one-increment contact law, and the corrections
pick another one than the DEM's path (docs/certificate.md, "With increments from rest at 1e-6").
``DemEscalation(sliding=True)`` hands those cell-increments to the DEM too (``DemEscalation.sliding``,
``DemEscalation.escalated``); the package's hybrids do not (measured only:
studies/bench_ann_equilibrium.py ``--escalation sliding``).

Sign convention: compression positive (moments as the DEM backend's ``CellResponse``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.mesostructures.mesostructure import Mesostructure

if TYPE_CHECKING:
    from warp_hcell.database.probing import ProbeContext
    from warp_hcell.dem.model import DemModel


RELEASE_RULE_AFTER = ("a free grain moved and no pair presses it above the equilibrium tolerance: the corrections "
                      "start again with that grain at rest")
"""The earlier rule, in words: a released grain is found after the balance (``DemEscalation.released``) and its cell
balanced again with that grain starting at rest."""
RELEASE_RULE = ("a free grain that no pair presses above the equilibrium tolerance at the start of the increment starts "
                "the corrections at rest; one that moved and no pair presses: the corrections start again with that "
                "grain at rest")
"""What the hybrid does with the grains that nothing presses, in words (``homogenization.ann.cell.AnnCell``): those
resting at the start of the increment (``DemEscalation.resting_dofs``) start the balance at rest, and a cell whose
other grains end released (``DemEscalation.released``) is balanced again with them at rest too. A certificate of a
hybrid with the escalation records its rule (``dem_escalation_rule``) and covers that rule only."""
RELEASE_RULE_DRAG = RELEASE_RULE + ("; one that started at rest, moved and no pair presses at the end moves as the "
                                     "DEM's relaxation from rest moves it, the friction of its contacts included")
"""``RELEASE_RULE``, then the grains that started the corrections at rest and end released (pushed lightly: the balance
moved them along the contact normal only) relaxed as the DEM does from rest, the other grains following the balance
(``homogenization.ann.relaxation``; ``AnnCell._dragged``, counted in ``n_relaxed``). CPU only; elsewhere as ``RELEASE_RULE``."""
RELAX_RATIO = 1e-6
"""Force ratio of the relaxed free DOFs (over the cell's largest normal force at the balanced end) that ends the
relaxation of ``RELEASE_RULE_DRAG`` (``DemEscalation.relaxed``), the DEM's ``force_tolerance`` [-]."""
RELAX_SUBSTEPS = 20_000
"""The most substeps of that relaxation per cell-increment [-]."""
RELEASE_RULES = (RELEASE_RULE, RELEASE_RULE_AFTER, RELEASE_RULE_DRAG)
"""The rules the CPU hybrid runs; a certificate recording one of them runs with it (new certificates: ``RELEASE_RULE``
unless asked)."""


class DemEscalation:
    """The DEM's increment of learning states of cells of ``meso`` (the model's own mesostructure), from rest.

    Batches are padded to a power of two cells (the last cell repeated) and each size keeps its DEM cell
    model and DEM model, so that the next call of that size reuses them and their integrator (building
    them costs more than stepping a few cells).

    Args:
        meso: the mesostructure the model was trained on (its learning state is the model's).
        contact_law: the model's contact law; contact_tolerance: its DEM's (``DemSettings.contact_tolerance``).
        force_ratio: the hybrid's equilibrium tolerance [-] (``released``).
        sliding: also the cells where a grain free along every axis slides (``escalated``).
    """

    SLIDING_CAP = 1.0 - 1e-9
    """A contact slides where its tangential force is at least this fraction of mu times its normal force [-]."""

    def __init__(self, meso: Mesostructure, contact_law: ContactLaw, contact_tolerance: float, *,
                 force_ratio: float = DemSettings().force_tolerance, sliding: bool = False) -> None:
        self.meso = meso
        self.force_ratio = float(force_ratio)
        self.with_sliding = bool(sliding)
        self.schema = meso.schema()
        self.contact_law = contact_law
        self.contact_tolerance = float(contact_tolerance)
        self._batches: dict[int, tuple[ProbeContext, DemModel]] = {}
        pairs, free_dofs, n_grains = self.schema.pairs, self.schema.free_dofs, self.schema.radius.shape[0]
        loose = np.bincount(free_dofs[:, 0], minlength=n_grains) == self.schema.dim
        self._loose_pairs = loose[pairs[:, 0]] | loose[pairs[:, 1]]
        as_array = lambda a, dtype=np.float64: np.ascontiguousarray(a, dtype=dtype)  # noqa: E731
        self._reference_position = as_array(self.schema.reference_position)
        self._reference_size = as_array(self.schema.reference_cell_size)
        self._free_dofs, self._pairs = as_array(free_dofs, np.int64), as_array(pairs, np.int64)
        self._rsum = as_array(self.schema.radius[pairs[:, 0]] + self.schema.radius[pairs[:, 1]])
        widen = 1.0 + self.contact_tolerance
        self._cut2 = (self._rsum * widen) * (self._rsum * widen)

    def sliding(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray) -> np.ndarray:
        """bool (n,): cells of the learning states (cell_size (n, dim) [m], free_position (n, n_free) [m],
        shear_force (n, ``*schema.shear_shape``) [N]) where a pair of a grain free along every axis is in
        contact, pressed (f_n > 0) and sliding: abs(f_s) >= ``SLIDING_CAP`` mu f_n."""
        from warp_hcell.database.learning_state import evaluate  # noqa: PLC0415 (the database: where a cell is tested)

        ev = evaluate(self.schema, cell_size, free_position, shear_force, self.contact_law, self.contact_tolerance)
        normal = ev["normal_force"]
        tangential = np.abs(ev["shear_force"]) if ev["shear_force"].ndim == 2 else np.linalg.norm(ev["shear_force"], axis=-1)
        slides = (ev["contact"] > 0) & (normal > 0.0) & (tangential >= self.SLIDING_CAP * self.contact_law.mu * normal)
        return np.any(slides & self._loose_pairs, axis=1)

    def escalated(self, cell_size: np.ndarray, free_before: np.ndarray, free_after: np.ndarray,
                  shear_after: np.ndarray) -> np.ndarray:
        """bool (n,): the cells handed to the DEM, ``released``, or with ``sliding=True`` also ``sliding`` at
        the end of the increment (cell_size, free_after, shear_after: the state after it)."""
        cells = self.released(cell_size, free_before, free_after)
        return cells | self.sliding(cell_size, free_after, shear_after) if self.with_sliding else cells

    def released(self, cell_size: np.ndarray, free_before: np.ndarray, free_after: np.ndarray) -> np.ndarray:
        """bool (n,): cells with a free grain that moved over the increment (a free coordinate changed) and
        that nothing presses at its end: each of its pairs' normal force is at most ``force_ratio`` times the
        cell's largest (the resolution of the corrections' balance: a grain that only one neighbour pushed
        ends in touch with such a force, which the corrections cannot tell from none); cell_size (n, dim)
        [m] and free_after (n, n_free) [m]: the state after the increment, free_before: before it. Compiled
        (``homogenization.ann.released.find_released``): the operations of ``learning_state.pair_normal_forces``,
        cells innermost."""
        return self.released_dofs(cell_size, free_before, free_after).any(axis=1)

    def released_dofs(self, cell_size: np.ndarray, free_before: np.ndarray, free_after: np.ndarray) -> np.ndarray:
        """bool (n, n_free): the free DOFs of the grains that ``released`` finds (same arguments)."""
        return self._test(cell_size, free_before, free_after, False)

    def resting_dofs(self, cell_size: np.ndarray, free_position: np.ndarray) -> np.ndarray:
        """bool (n, n_free): the free DOFs of the grains that no pair presses in the state (cell_size (n, dim),
        free_position (n, n_free) [m]): each of their pairs' normal force is at most ``force_ratio`` times the
        cell's largest (``released``'s test without the motion; every grain of a cell that carries no force)."""
        return self._test(cell_size, free_position, free_position, True)

    def _test(self, cell_size, free_before, free_after, every: bool) -> np.ndarray:
        """The DOFs of ``homogenization.ann.released.find_released`` (n, n_free), cells first."""
        from homogenization.ann.released import find_released  # noqa: PLC0415 (numba: compiled on first use)

        cells_last = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64).T)  # noqa: E731
        n = np.shape(cell_size)[0]
        out, dofs = np.empty(n, dtype=np.bool_), np.empty((self._free_dofs.shape[0], n), dtype=np.bool_)
        find_released(cells_last(cell_size), cells_last(free_before), cells_last(free_after), self._reference_position,
                      self._reference_size, self._free_dofs, self._pairs, self._rsum, self._cut2,
                      float(self.contact_law.kn), self.force_ratio, out, dofs, bool(every))
        return dofs.T

    def relaxed(self, x0: np.ndarray, x1: np.ndarray, shear_force: np.ndarray, d_eps: np.ndarray, pushed: np.ndarray, *,
                ratio: float = RELAX_RATIO, max_substeps: int = RELAX_SUBSTEPS,
                settings: DemSettings = DemSettings()) -> tuple[np.ndarray, np.ndarray]:
        """(free positions (m, n_free) [m], substeps (m,) int64): ``RELEASE_RULE_DRAG``'s relaxation
        (``homogenization.ann.relaxation.relax``) of the free DOFs ``pushed`` (m, n_free) bool of m cells, the
        others kept at the balance's; x0, x1: the grain centres (m, n_grains, 3) [m] before the increment and after
        the balance, ``shear_force`` (m, n_pairs, 3) [N] the springs before it, ``d_eps`` (m, 3) the probe.
        ``settings``: the DEM's density, time step, damping and strain per substep from rest; ``ratio`` and
        ``max_substeps``: where the relaxation stops (the largest normal force: at x1)."""
        from homogenization.ann.relaxation import relax  # noqa: PLC0415 (compiled on first use)

        free_dofs = self._free_dofs
        x0, x1 = np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(x1, dtype=np.float64)
        simulated = np.zeros(x0.shape, dtype=np.bool_)
        simulated[:, free_dofs[:, 0], free_dofs[:, 1]] = pushed
        b = x1[:, self._pairs[:, 1]] - x1[:, self._pairs[:, 0]]
        distance = np.sqrt(b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1] + b[..., 2] * b[..., 2])
        touching = distance <= self._rsum * (1.0 + self.contact_tolerance)
        fn_max = np.where(touching, self.contact_law.kn * np.maximum(self._rsum - distance, 0.0), 0.0).max(axis=1)
        radius = np.ascontiguousarray(self.schema.radius, dtype=np.float64)
        mass = settings.density * dimension(self.schema.dim).grain_measure(radius)  # the DEM's (DemModel)
        dt = settings.dt_factor * float(np.sqrt(mass.min() / self.contact_law.kn))
        largest = np.abs(np.asarray(d_eps, dtype=np.float64)).max(axis=1)
        n_drive = np.maximum(np.ceil(largest / settings.rest_strain_per_substep), 1.0).astype(np.int64)
        free_mask = np.zeros(x0.shape[1:], dtype=np.bool_)
        free_mask[free_dofs[:, 0], free_dofs[:, 1]] = True
        x_out, substeps = np.empty_like(x0), np.empty(x0.shape[0], dtype=np.int64)
        relax(x0, x1, simulated, np.ascontiguousarray(shear_force, dtype=np.float64), self._pairs, radius, 1.0 / mass,
              dt, float(self.contact_law.kn), float(self.contact_law.kt), float(self.contact_law.mu),
              self.contact_tolerance, float(settings.damping), n_drive, fn_max, float(ratio), int(max_substeps),
              free_mask, x_out, substeps)
        return np.where(pushed, x_out[:, free_dofs[:, 0], free_dofs[:, 1]], x1[:, free_dofs[:, 0], free_dofs[:, 1]]), substeps

    def _batch(self, n: int) -> tuple[ProbeContext, DemModel]:
        """The probe context and the DEM model of batches of ``n`` cells (built once)."""
        if n not in self._batches:
            from warp_hcell.dem.cell import DemCell  # noqa: PLC0415 (Warp only where a cell escalates)
            from warp_hcell.dem.model import DemModel  # noqa: PLC0415
            from warp_hcell.database.probing import ProbeContext  # noqa: PLC0415

            settings = DemSettings(contact_tolerance=self.contact_tolerance).from_rest
            cell_model = DemCell(self.contact_law, float(self.meso.radius.mean()), settings=settings, threads=1)
            model = DemModel.build(self.meso, n, contact_law=self.contact_law, settings=settings)
            self._batches[n] = (ProbeContext(cell_model, self.meso, self.schema, {}, self.contact_law,
                                             self.contact_tolerance), model)
        return self._batches[n]

    def advance(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                d_eps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The DEM's increment of the cells (first axis n) from their learning states at rest.

        Returns (cell_size (n, dim) [m], free_position (n, n_free) [m], shear_force (capped, zero out of
        contact: the learning state's) [N], moment (n, dim, dim) [N m], area (n,) [m^dim]) after it, and whether
        each cell's DEM reached equilibrium (bool (n,))."""
        from warp_hcell.dem.cell import DemCellState  # noqa: PLC0415 (Warp only where a cell escalates)
        from warp_hcell.dem.state import DemState  # noqa: PLC0415
        from warp_hcell.database.learning_state import evaluate, free_coordinates  # noqa: PLC0415
        from warp_hcell.database.probing import step_from_rest  # noqa: PLC0415

        n = cell_size.shape[0]
        rows = np.minimum(np.arange(1 << (n - 1).bit_length()), n - 1)
        context, model = self._batch(rows.size)
        _, after, response = step_from_rest(
            context, *(np.asarray(a)[rows] for a in (cell_size, free_position, shear_force, d_eps)),
            state_of=lambda arrays: DemCellState(model, DemState.from_numpy(arrays, model.device)))
        free = free_coordinates(self.schema, after["position"][:n])
        shear = evaluate(self.schema, after["cell_size"][:n], free, after["shear_force"][:n], self.contact_law,
                         self.contact_tolerance)["shear_force"]
        return (after["cell_size"][:n], free, shear, np.asarray(response.moment)[:n],
                np.asarray(response.area)[:n], np.asarray(after["converged"])[:n] == 1)
