"""The material points of an element test: their oriented cells, their saved state, trials and acceptance.

``material_points(cell_model, mesostructure, n_points, ...)`` builds n material points of one
mesostructure (``homogenization.material.homogenised``), oriented by
``homogenization.material.orientation`` (in 3D with the mesostructure's own spin period and kinematics
``orientation.cell_kinematics``: e.g. ``hcell3d-axisym``). ``MaterialPoints`` holds the state of
the last accepted increment; a trial updates every point from it (one batched ``step``), and
``accept`` takes a trial for the points of a mask, the others keeping their state, so a point's
history does not depend on the batch it runs in.

Macro increments are in the material's Voigt form (2D (11, 22, 2 x 12), 3D (11, 22, 33, 23, 13, 12)),
shape (n_points, n_voigt) [-]; stresses [N/m] (2D) or [Pa] (3D); compression positive.
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np

from homogenization.material import orientation as orient_mod
from homogenization.material import opening_spread
from homogenization.material.homogenised import HomogenisedMaterial, MaterialState, MaterialUpdate
from warp_hcell.core.contract import CellModel
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.mesostructure import Mesostructure


def orientation_set(mesostructure: Mesostructure, *, n_orientations: int, fabric_anisotropy: float = 0.0,
                    fabric_direction_deg: float = 0.0, lebedev_order: int, n_spins: int,
                    spin_period_deg: float | None = None, staggered_spins: bool = True) -> orient_mod.OrientationSet:
    """The orientation set of cells of ``mesostructure``: 2D ``n_orientations`` with the fabric weights, 3D
    ``lebedev_order`` x ``n_spins`` with the cell's spin period (``spin_period_deg`` None) and kinematics;
    ValueError for an anisotropic fabric in 3D."""
    if getattr(mesostructure, "dim", 2) == 2:
        return orient_mod.orientations(n_orientations, anisotropy=fabric_anisotropy, direction_deg=fabric_direction_deg)
    if fabric_anisotropy:
        raise ValueError("an anisotropic fabric is not available in 3D yet (fabric_anisotropy must be 0)")
    period = mesostructure.spin_period_deg() if spin_period_deg is None else spin_period_deg
    return orient_mod.orientations_3d(lebedev_order, n_spins, spin_period_deg=period, staggered=staggered_spins,
                                      kinematics=orient_mod.cell_kinematics(mesostructure))


def material_points(cell_model: CellModel, mesostructure: Mesostructure, n_points: int,
                    orient: orient_mod.OrientationSet | None = None, **orientations: Any) -> MaterialPoints:
    """``n_points`` touching, force-free material points of ``mesostructure`` cells oriented by ``orient``
    (None: ``orientation_set(mesostructure, **orientations)``, once per family of opening angles where
    the cell model declares them: ``opening_spread.FAMILIES_ATTRIBUTE``)."""
    if orient is None:
        orient = orientation_set(mesostructure, **orientations)
        if getattr(cell_model, opening_spread.FAMILIES_ATTRIBUTE, False):
            orient = opening_spread.replicate(orient)
    return MaterialPoints(HomogenisedMaterial(cell_model, orient, mesostructure, n_points))


class MaterialPoints:
    """n material points under load: the material, the state of the last accepted increment, and what the
    trials since the last recorded increment cost.

    Attributes:
        material: the ``HomogenisedMaterial`` of n points.
        state: ``MaterialState`` of the last accepted increment.
        peak: per point, the largest ``|sigma|`` component accepted so far [N/m or Pa], shape (n,).
        call_totals: each backend diagnostic summed over the trials since the last recorded increment.
        accepted_diagnostics: the backend diagnostics of the last accepted trial.
        last_trial: the macro increment (n, n_voigt) of the last trial with finite increments (None before).
    """

    def __init__(self, material: HomogenisedMaterial) -> None:
        self.material = material
        self.model = material.model
        self.state = material.init_state()
        self.n = material.n_points
        self.dim = material.dim
        self.n_voigt = material.n_voigt
        self.dimension = dimension(self.dim)
        self.unit = self.dimension.stress_unit
        self.peak = np.zeros(self.n)
        self.call_totals: dict[str, float] = {}
        self.accepted_diagnostics: dict[str, Any] = {}
        self.last_trial: np.ndarray | None = None
        self.renewal: Any = None
        """A rule applied to every trial (``within``) and to the accepted state after every recorded increment
        (``advance``, in ``end_increment``), e.g. ``homogenization.material.critical_state.Renewal``; None: none."""

    @property
    def stress(self) -> np.ndarray:
        """Stress of the last accepted increment, shape (n, 3 or 6)."""
        return self.state.stress

    def mean(self, stress: np.ndarray) -> np.ndarray:
        """p = tr(sigma) / dim of stresses (n, 3 or 6), shape (n,)."""
        return self.dimension.mean_stress(stress)

    def trial(self, d_e: np.ndarray, *, with_tangent: bool = False) -> MaterialUpdate:
        """Every point updated by its macro increment ``d_e`` (n, n_voigt) from the saved state (pure)."""
        update = self.material.update(self.state, d_e, with_tangent=with_tangent)
        if self.renewal is not None:
            update = self.renewal.within(self.state, update)
        if np.all(np.isfinite(d_e)):
            self.last_trial = np.array(d_e, dtype=np.float64)
        for name, value in update.diagnostics.items():
            self.call_totals[name] = self.call_totals.get(name, 0.0) + float(value)
        return update

    def accept(self, update: MaterialUpdate, mask: np.ndarray | None = None) -> None:
        """Take the trial ``update`` for the points of ``mask`` (n,) (None: every point); the others keep theirs."""
        peak = np.maximum(self.peak, np.abs(update.stress).max(axis=1))
        if mask is None or mask.all():
            self.state, self.peak = update.state, peak
        elif mask.any():
            self.state, self.peak = self._merged(update.state, mask), np.where(mask, peak, self.peak)
        else:
            return
        self.accepted_diagnostics = update.diagnostics

    def end_increment(self) -> None:
        """Apply ``renewal`` (if any) to the accepted state, between two increments."""
        if self.renewal is not None:
            self.state = self.renewal.advance(self.state)

    def _merged(self, new: MaterialState, mask: np.ndarray) -> MaterialState:
        old = self.state
        cells_mask = np.repeat(mask, self.material.orient.n_cells)
        old_arrays = self.model.state_to_arrays(old.cells)
        new_arrays = self.model.state_to_arrays(new.cells)
        cells = self.model.state_from_arrays({k: np.where(cells_mask, new_arrays[k], old_arrays[k]) for k in old_arrays})
        return MaterialState(cells, np.where(mask, new.J, old.J), np.where(mask[:, None], new.strain, old.strain),
                             np.where(mask[:, None], new.stress, old.stress))

    def replace_cells(self, cell_model: CellModel, cells: Any) -> None:
        """Go on with other cells at every point (e.g. ``warp_hcell.dem.erosion.erode_state``'s reduced cells):
        ``cell_model`` and its state ``cells`` of the same orientations; J, strain and stress stay, so the
        macro volume V0 J carries on."""
        self.material.model = self.model = cell_model
        self.material.returns_tangent = "with_tangent" in inspect.signature(cell_model.step).parameters
        self.state = MaterialState(cells, self.state.J, self.state.strain, self.state.stress)

    def axes(self) -> np.ndarray:
        """Each cell's axis n in the macro frame, shape (n_cells, dim)."""
        return self.material.orient.axes
