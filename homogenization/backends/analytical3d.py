"""Closed-form ten-sphere H-cell: two planar H-cells that share their axial grains.

The 3D H-cell (docs/model.md) is made of two H-cell hexagons in the orthogonal planes (n, t1)
(plane A: grains 1-6) and (n, t2) (plane B: grains 1, 4 and 7-10), sharing the axial grains 1
and 4. The axial grains are driven along n, t1 and t2; each lateral grain is driven along its
plane's lateral axis (scaled by l2 or l3) and out of its plane (held at 0), and free along n.

Decoupling. While no lateral grain of one plane touches a lateral grain of the other, the only
free DOF of a lateral grain (its n coordinate) sees the forces of its two axial neighbours and of
its type-2 partner, all in its own plane; the axial grains are driven. So plane A is exactly the
planar H-cell at (l1, l2) and plane B the planar H-cell at (l1, l3): each has its own y2, found
by the one-unknown equilibrium solve of the planar analytical cell
(``homogenization.backends.analytical.AnalyticalCell``), and

    S_nn = S_nn(A) + S_nn(B) - kn <D - l1> l1,   S_t1t1 = S_tt(A),   S_t2t2 = S_tt(B),

off-diagonal terms zero (the pathological contact 1-4, which both planar cells count, is
counted once). The tangent follows the same way from the two planar tangents. Where it stops
holding: a lateral grain of plane A and one of plane B are sqrt((y2A - y2B)^2 + (l2/2)^2 +
(l3/2)^2) apart; for equal grains they touch once (l2^2 + l3^2)/4 + (y2A - y2B)^2 < D^2 (near
alpha = 45 deg at the touching state). Such a contact is outside the closed form: ``step``
counts the cells in ``diagnostics["n_cross_plane"]`` (the DEM models it).

Kinematics: ``step`` takes the cell-axis strains as given. The cell kind ``hcell3d-axisym`` has the same
grains and is modelled here unchanged; its axisymmetric kinematics are applied where the macro
increment is localised (``homogenization.material.orientation``, ``AXISYMMETRIC_MAP``), so both planes then
receive the same lateral strain.

Cell volume: the polyhedron through the ten centres (``polyhedron_volume`` over
``HCELL3D_FACES``), the 3D counterpart of the planar cell's hexagon.

Sign convention: compression and contraction positive. Local frame index 0 = n, 1 = t1, 2 = t2.
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from homogenization.backends.analytical import AnalyticalCell, AnalyticalState, cell_alpha0, plain_cell_alpha0
from warp_hcell.core.contact import PairLaw, reduced_radius_root
from warp_hcell.core.contract import CellResponse
from warp_hcell.core.parameters import ContactLaw, hertz_normal_modulus, hertz_shear_stiffness_modulus, HertzMindlinLaw, Law
from warp_hcell.mesostructures import hcell
from warp_hcell.mesostructures.hcell import plain_alpha0_3d
from warp_hcell.mesostructures.mesostructure import Mesostructure, polyhedron_volume

PLANE_B_GRAINS = (1, 2, 4, 5)
"""Indices (0-based) in a planar H-cell of the lateral grains that become grains 7, 8, 9, 10 of plane B."""
HCELL3D_FACES = hcell.h_cell_3d_faces()
"""Outer faces of the ten-sphere H-cell."""


def hcell3d_positions(plane_a: np.ndarray, plane_b: np.ndarray) -> np.ndarray:
    """Ten centres (n_cells, 10, 3) [m] from the planar positions (n_cells, 6, 2) of planes A and B."""
    n_cells = plane_a.shape[0]
    x = np.zeros((n_cells, 10, 3))
    x[:, :6, 0], x[:, :6, 1] = plane_a[..., 0], plane_a[..., 1]
    x[:, 6:, 0], x[:, 6:, 2] = plane_b[:, PLANE_B_GRAINS, 0], plane_b[:, PLANE_B_GRAINS, 1]
    return x


class Analytical3DState(NamedTuple):
    """Batch of ten-sphere H-cells: the planar states of plane A (n, t1) and plane B (n, t2).

    Both share l1 (the axial grains); plane A's l2 is the cell's l2, plane B's l2 its l3.
    """

    a: AnalyticalState
    b: AnalyticalState


class Analytical3DCell:
    """Closed-form ten-sphere H-cell (module docstring), vectorised over cells.

    Args:
        contact_law: contact stiffnesses and friction: the linear law or the Hertz-Mindlin law of
            spheres (``warp_hcell.core.parameters.CONTACT_LAWS``).
        radius: grain radius r [m] (all ten spheres equal).
        tolerance, max_iterations: of the planar solve (``AnalyticalCell``).
    """

    name = "analytical"
    dim = 3
    """Spatial dimension of the cells."""

    def __init__(self, contact_law: Law, radius: float, *, tolerance: float = 1e-10,
                 max_iterations: int = 60) -> None:
        self.plane = AnalyticalCell(contact_law, radius, tolerance=tolerance, max_iterations=max_iterations)
        self.kn = self.plane.kn
        self.diameter = self.plane.diameter

    @classmethod
    def with_cell_laws(cls, kn: np.ndarray, kt_over_kn: np.ndarray, phi_g_deg: np.ndarray, radius: float,
                       alpha0_deg: np.ndarray | None = None, **options) -> Analytical3DCell:
        """A backend whose cell i has its own contact law and opening angle (a population of
        parameter sets as one batch), as ``AnalyticalCell.with_cell_laws``: both planes of cell i
        use its kn [N/m], kt_over_kn [-] and phi_g_deg [deg] (shape (n_cells,)) and start at its
        alpha0_deg [deg] (shape (n_cells,); None: the mesostructure's). Every batch it steps must
        have these n_cells, in this order.

        Raises:
            ValueError: (one line) a value outside the ranges of ``ContactLaw`` or of the 3D cell.
        """
        model = cls(ContactLaw(), radius, **options)
        model.plane = AnalyticalCell.with_cell_laws(kn, kt_over_kn, phi_g_deg, radius, alpha0_deg=alpha0_deg,
                                                    **options)
        model.kn = model.plane.kn
        return model

    @classmethod
    def with_hertz_cell_laws(cls, shear_modulus: np.ndarray, poisson: np.ndarray, phi_g_deg: np.ndarray,
                             radius: float, alpha0_deg: np.ndarray | None = None, **options) -> Analytical3DCell:
        """``with_cell_laws`` of the Hertz-Mindlin law: cell i has the grain shear modulus
        shear_modulus[i] [Pa] (> 0), Poisson ratio poisson[i] [-] (in [0, 0.5)), friction angle
        phi_g_deg[i] [deg] and opening angle alpha0_deg[i] [deg] (shape (n_cells,) each).

        Raises:
            ValueError: (one line) a value outside the ranges of ``HertzMindlinLaw``.
        """
        G, nu, phi = np.broadcast_arrays(*(np.array(v, dtype=np.float64, ndmin=1)
                                           for v in (shear_modulus, poisson, phi_g_deg)))
        for k in np.flatnonzero(~(np.isfinite(G) & (G > 0.0) & (nu >= 0.0) & (nu < 0.5) & (phi >= 0.0) & (phi < 90.0))):
            HertzMindlinLaw(float(G[k]), float(nu[k]), float(phi[k]))  # raises, naming the value
        model = cls(HertzMindlinLaw(), radius, **options)
        plane = model.plane
        root = reduced_radius_root(plane.radius, plane.radius)
        plane.law = PairLaw("hertz-mindlin", hertz_normal_modulus(G, nu) * root,
                            hertz_shear_stiffness_modulus(G, nu) * root)
        plane.kn, plane.kt = plane.law.kn, plane.law.kt
        plane.mu = np.tan(np.radians(phi))
        plane.contact_law = None
        plane.f_tolerance = plane.tolerance * plane.stiffness_scale * plane.radius
        if alpha0_deg is not None:
            plane.cell_alpha0_deg = np.array(alpha0_deg, dtype=np.float64, ndmin=1)
            hcell.touching_cells(plane.cell_alpha0_deg, plane.cell_alpha0_deg.size, plane.diameter)  # range check
        model.kn = plane.kn
        return model

    @staticmethod
    def check_mesostructure(meso: Mesostructure) -> float:
        """Opening angle alpha0 [deg] of ``meso`` if it is the cell this backend models.

        Raises:
            ValueError: (one line) ``meso`` is not the touching ten-equal-sphere cell of orthogonal planes
                (``warp_hcell.mesostructures.hcell.plain_alpha0_3d``).
        """
        return plain_cell_alpha0(meso, plain_alpha0_3d, "the plain ten-sphere H-cell only in 3D (equal touching "
                                                        "spheres, planes 90 deg apart)", 3)

    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int) -> Analytical3DState:
        """Touching, force-free cells at the opening angle of each cell's mesostructure (``check_mesostructure``),
        or at the per-cell angles of ``with_cell_laws``.

        Raises:
            ValueError: (one line) a mesostructure that is not the plain ten-sphere cell, or whose spheres
                have another radius than this backend's.
        """
        alpha0_deg = cell_alpha0(mesostructure, n_cells, self.check_mesostructure, self.plane.radius, "spheres")
        if self.plane.cell_alpha0_deg is not None:
            alpha0_deg = np.broadcast_to(self.plane.cell_alpha0_deg, (int(n_cells),))
        return self.touching_state(alpha0_deg, n_cells)

    def touching_state(self, alpha0_deg: float | np.ndarray, n_cells: int) -> Analytical3DState:
        """Touching, force-free cells at opening angle(s) ``alpha0_deg`` [deg] (scalar or (n_cells,))."""
        return Analytical3DState(*(self.plane.touching_state(alpha0_deg, n_cells) for _ in range(2)))

    def _pathological_axial(self, l1: np.ndarray) -> np.ndarray:
        """kn <D - l1> l1 [N m] (the contact law's force at overlap D - l1, times l1): the contact 1-4
        that both planar cells add to S_nn."""
        if self.plane.hertz:
            return self.plane.law.normal(self.diameter - l1) * l1
        return self.kn * np.maximum(self.diameter - l1, 0.0) * l1

    def step(self, state: Analytical3DState, d_eps_local: np.ndarray, *,
             with_tangent: bool = False) -> tuple[Analytical3DState, CellResponse]:
        """Advance every cell by (d_eps_n, d_eps_t1, d_eps_t2) [-], shape (n_cells, 3); ``state`` untouched.

        Returns the new state and its response: moment (n_cells, 3, 3) [N m] and volume
        (``area``) (n_cells,) [m^3]; ``tangent`` (n_cells, 3, 3) d(S_nn, S_t1t1, S_t2t2)/d(d_eps_n,
        d_eps_t1, d_eps_t2) when asked. Diagnostics: the planar solves' counts summed, and
        ``n_cross_plane``, cells where a lateral grain of one plane reaches one of the other.
        """
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        new_a, response_a = self.plane.step(state.a, d_eps[:, [0, 1]], with_tangent=with_tangent)
        new_b, response_b = self.plane.step(state.b, d_eps[:, [0, 2]], with_tangent=with_tangent)
        new = Analytical3DState(new_a, new_b)
        moment = self._moment(new, response_a.moment, response_b.moment)
        tangent = None
        if with_tangent:
            tangent = np.zeros((moment.shape[0], 3, 3))
            ta, tb = response_a.tangent, response_b.tangent
            l1 = new_a.l1
            closed14 = (self.diameter - l1 > 0.0)
            if self.plane.hertz:
                law, overlap = self.plane.law, self.diameter - l1
                slope = law.normal(overlap) - law.normal_stiffness(overlap) * l1
            else:
                slope = self.kn * (self.diameter - 2.0 * l1)
            d_axial = np.where(closed14, slope, 0.0) * -state.a.l1
            tangent[:, 0, 0] = ta[:, 0, 0] + tb[:, 0, 0] - d_axial
            tangent[:, 0, 1], tangent[:, 0, 2] = ta[:, 0, 1], tb[:, 0, 1]
            tangent[:, 1, 0], tangent[:, 1, 1] = ta[:, 1, 0], ta[:, 1, 1]
            tangent[:, 2, 0], tangent[:, 2, 2] = tb[:, 1, 0], tb[:, 1, 1]
        diagnostics = {key: response_a.diagnostics[key] + response_b.diagnostics[key]
                       for key in response_a.diagnostics}
        diagnostics["n_cross_plane"] = float(np.count_nonzero(self.cross_plane_contact(new)))
        return new, CellResponse(moment, self.volume(new), diagnostics, tangent)

    def _moment(self, state: Analytical3DState, moment_a: np.ndarray, moment_b: np.ndarray) -> np.ndarray:
        moment = np.zeros((moment_a.shape[0], 3, 3))
        moment[:, 0, 0] = moment_a[:, 0, 0] + moment_b[:, 0, 0] - self._pathological_axial(state.a.l1)
        moment[:, 1, 1] = moment_a[:, 1, 1]
        moment[:, 2, 2] = moment_b[:, 1, 1]
        return moment

    def positions(self, state: Analytical3DState) -> np.ndarray:
        """Grain centres (n_cells, 10, 3) [m], cell centre at the origin."""
        return hcell3d_positions(hcell.grain_positions(state.a.l1, state.a.l2, state.a.y2),
                                 hcell.grain_positions(state.b.l1, state.b.l2, state.b.y2))

    def volume(self, state: Analytical3DState) -> np.ndarray:
        """V_cell [m^3] of every cell: the polyhedron through the ten centres."""
        return polyhedron_volume(self.positions(state), HCELL3D_FACES)

    def cross_plane_contact(self, state: Analytical3DState) -> np.ndarray:
        """bool (n_cells,): a lateral grain of plane A within one diameter of a lateral grain of plane B."""
        gap2 = (state.a.y2 - state.b.y2) ** 2 + 0.25 * (state.a.l2 ** 2 + state.b.l2 ** 2)
        return gap2 < self.diameter ** 2

    def response(self, state: Analytical3DState) -> CellResponse:
        """Meso-stress of ``state`` without advancing it."""
        ra, rb = self.plane.response(state.a), self.plane.response(state.b)
        return CellResponse(self._moment(state, ra.moment, rb.moment), self.volume(state))

    def observables(self, state: Analytical3DState) -> dict[str, np.ndarray]:
        """Per-cell quantities (n_cells,): ``l1, l2, l3`` [m], the planar observables of each plane with
        suffix ``_a`` / ``_b`` (``alpha_deg``, ``d1``, ``d2``, ``N1``, ``N2``, ``T1``, ``closed1``,
        ``closed2``), ``S_nn, S_t1t1, S_t2t2`` [N m], ``volume`` [m^3], ``cross_plane`` (bool) and the grain
        centres ``x_n{i}, x_t1{i}, x_t2{i}`` [m] (i = 1-based label, cell centre at the origin)."""
        response = self.response(state)
        out: dict[str, np.ndarray] = {"l1": state.a.l1, "l2": state.a.l2, "l3": state.b.l2}
        for suffix, plane in (("a", state.a), ("b", state.b)):
            planar = self.plane.observables(plane)
            for key in ("alpha_deg", "d1", "d2", "N1", "N2", "T1", "closed1", "closed2"):
                out[f"{key}_{suffix}"] = planar[key]
        out.update(S_nn=response.moment[:, 0, 0], S_t1t1=response.moment[:, 1, 1], S_t2t2=response.moment[:, 2, 2],
                   volume=response.area, cross_plane=self.cross_plane_contact(state))
        x = self.positions(state)
        for g in range(x.shape[1]):
            for axis, name in enumerate(("n", "t1", "t2")):
                out[f"x_{name}{g + 1}"] = x[:, g, axis]
        return out

    def take(self, state: Analytical3DState, index: np.ndarray) -> Analytical3DState:
        """Cells ``state[index]`` (int array, repetition allowed)."""
        return Analytical3DState(self.plane.take(state.a, index), self.plane.take(state.b, index))

    def state_to_arrays(self, state: Analytical3DState) -> dict[str, np.ndarray]:
        """Both planes' fields, prefixed ``a_`` and ``b_``."""
        return {f"{prefix}_{key}": value for prefix, plane in (("a", state.a), ("b", state.b))
                for key, value in self.plane.state_to_arrays(plane).items()}

    def state_from_arrays(self, arrays: Mapping[str, Any]) -> Analytical3DState:
        """Inverse of ``state_to_arrays``."""
        return Analytical3DState(*(self.plane.state_from_arrays({key: arrays[f"{prefix}_{key}"]
                                                                 for key in AnalyticalState._fields})
                                   for prefix in ("a", "b")))
