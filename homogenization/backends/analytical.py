"""Closed-form H-cell backend (spec section 6): a cell is one planar H-cell per lateral axis, all sharing the
axial grains 1 and 4.

The planar cell (``dimension(2)``) is one plane, (n, t): six disks. The ten-sphere cell (``dimension(3)``,
docs/model.md section 14) is two, (n, t1) with grains 1-6 and (n, t2) with grains 1, 4 and 7-10. Per increment
plane k takes (d_eps_n, d_eps_tk): l1 and its lateral length follow the imposed strain (spec section 3), and its
only unknown, y2 = d2/2, is found such that grain 2 is in equilibrium along n:

    f(y2) = N2 - N1 cos a - T1 sin a (- g2 T1) = 0,

with N1 = kn <D - d1>, N2 = kn <D - d2> and T1 the incremental tangential spring with a Coulomb cap evaluated
from the state at the start of the increment: T_trial = T1_old + kt d1_mid (a - a_old), T1 = clip(T_trial,
-mu N1, +mu N1); T1 = 0 whenever the type-1 contact is open. The solve is a safeguarded Newton iteration on the
whole batch, from the previous y2, inside a bracket in (0, l1/2]: where a Newton step leaves the bracket, y2
walks towards the root by doubling steps. Converged cells are frozen, so a cell's result does not depend on its
batch. Where both contacts are open y2 is kept; where f > 0 even at y2 = l1/2 (alpha = 90 deg) the cell is held
there.

The cell's Love-Weber moment sums its planes' with the axial contact 1-4, which every plane counts, counted
once:

    S_nn = sum_k S_nn(k) - (n_planes - 1) kn <D - l1> l1,   S_tktk = S_tt(k),   other components zero,

and so does the consistent tangent (``with_tangent=True``), from each plane's: implicit differentiation of
f(y2; l1, l2) = 0 in the regime the solve reached, dy2/dl = -(df/dl) / (df/dy2), with the partial derivatives of
``_partials``. The planes decouple while no lateral grain of one plane touches one of another (true for the
planar cell); ``step`` counts the cells where two planes' lateral grains come within one diameter in
``diagnostics["n_cross_plane"]`` (the DEM models that contact). V_cell is the hexagon's area (one plane) or the
polyhedron through the ten centres.

The Hertz-Mindlin law (``warp_hcell.core.parameters.HertzMindlinLaw``, spheres) replaces kn <D - d> by
kh <D - d>^(3/2) and kt by the mean Mindlin stiffness of the increment's type-1 overlaps (as the DEM's,
``warp_hcell.core.laws.hertz_mindlin``); the solve and the tangent are the same with the overlap-dependent
slopes.

Kinematics: ``step`` takes the cell-axis strains as given; the kinds ``hcell3d-axisym`` and ``hcell3d-sand``
are modelled unchanged, their kinematics applied where the macro increment is localised
(``homogenization.material.orientation``).

Sign convention: compression and contraction positive; T1 > 0 resists opening (alpha growing). Local frame:
index 0 = n, k = t_k.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from itertools import combinations
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from warp_hcell.core.contact import PairLaw, pair_law, reduced_radius_root
from warp_hcell.core.contract import CellResponse
from warp_hcell.core.dimension import Dimension, dimension
from warp_hcell.core.parameters import (
    HERTZ_DT_OVERLAP,
    check_positive,
    ContactLaw,
    hertz_normal_modulus,
    hertz_shear_stiffness_modulus,
    HertzMindlinLaw,
    Law,
)
from warp_hcell.mesostructures import hcell
from warp_hcell.mesostructures.mesostructure import Mesostructure, per_cell, polyhedron_volume_of_rows


class AnalyticalState(NamedTuple):
    """Batch of planar H-cells (the state of one plane); every field has shape (n_cells,).

    (l1, l2, y2) fix the geometry; the other fields are derived from it at the end of the
    increment that produced the state and kept so that the next increment starts from them.
    """

    l1: np.ndarray
    """Axial length, centre 1 to centre 4 [m]."""
    l2: np.ndarray
    """Distance between the plane's lateral columns [m] (the cell's l2, or l3 for the second plane)."""
    y2: np.ndarray
    """n-coordinate of grain 2, d2/2 [m]."""
    d1: np.ndarray
    """Type-1 branch length [m]."""
    alpha: np.ndarray
    """Opening angle [rad]."""
    N1: np.ndarray
    """Normal force of the type-1 contacts [N], compression positive."""
    N2: np.ndarray
    """Normal force of the type-2 contacts [N], compression positive."""
    T1: np.ndarray
    """Tangential force of the type-1 contacts [N], > 0 resists opening."""


class Analytical3DState(NamedTuple):
    """Batch of ten-sphere cells: the states of plane A (n, t1) and plane B (n, t2), which share l1."""

    a: AnalyticalState
    b: AnalyticalState


LATERAL_GRAINS = [1, 2, 4, 5]
"""Indices (0-based) in a plane's six grains of its lateral grains: those a second plane adds to the cell."""
TEN_SPHERE_FACES = hcell.h_cell_3d_faces()
"""Outer triangles of the ten-sphere cell."""


def cell_positions(planes: Sequence[AnalyticalState]) -> np.ndarray:
    """Grain centres (n_cells, 2 + 4 n_planes, 1 + n_planes) [m], cell centre at the origin: the first plane's
    six grains in (n, t1), then each further plane k's lateral grains in (n, tk) (``grain_rows``, reordered)."""
    return np.ascontiguousarray(np.moveaxis(grain_rows(planes), -1, 0))


def grain_rows(planes: Sequence[AnalyticalState]) -> np.ndarray:
    """``cell_positions`` laid out grain, then component first: shape (2 + 4 n_planes, 1 + n_planes, n_cells) [m]."""
    first = planes[0]
    n_planes = len(planes)
    x = np.zeros((2 + 4 * n_planes, 1 + n_planes, first.l1.shape[0]))
    x[:6, :2] = hcell.grain_rows(first.l1, first.l2, first.y2)
    for k, plane in enumerate(planes[1:], start=2):
        lateral = hcell.grain_rows(plane.l1, plane.l2, plane.y2)[LATERAL_GRAINS, :]
        rows = slice(4 * k - 2, 4 * k + 2)
        x[rows, 0], x[rows, k] = lateral[:, 0], lateral[:, 1]
    return x


def _hexagon_area(planes: Sequence[AnalyticalState], areas: Sequence[np.ndarray]) -> np.ndarray:
    return areas[0]


def _polyhedron_volume(planes: Sequence[AnalyticalState], areas: Sequence[np.ndarray]) -> np.ndarray:
    return polyhedron_volume_of_rows(grain_rows(planes), TEN_SPHERE_FACES)


def _cells_of(value: Any, keep: np.ndarray, n_cells: int) -> Any:
    """``value``'s entries of the cells ``keep`` if it holds one per cell (shape (n_cells,)), else ``value``."""
    return np.asarray(value)[keep] if np.ndim(value) == 1 and np.shape(value)[0] == n_cells else value


@dataclass(frozen=True)
class CellLayout:
    """How the planes make the closed form's cell of one dimension (``LAYOUTS``)."""

    dimension: Dimension
    """The cells' dimension: one plane per lateral axis (``frame[1:]``)."""
    state: Callable[..., Any]
    """The planes' states, one argument per plane -> the cell's state."""
    planes: Callable[[Any], tuple[AnalyticalState, ...]]
    """The cell's state -> its planes' states, in the order of the lateral axes."""
    prefixes: tuple[str, ...]
    """Prefix of each plane's fields in ``state_to_arrays``."""
    suffixes: tuple[str, ...]
    """Suffix of each plane's quantities in ``observables``."""
    plain_alpha0: Callable[[Mesostructure], tuple[float, float] | None]
    """(alpha0_deg, radius) of the plain cell of this dimension, None for another mesostructure."""
    models: str
    """What the backend models, as its refusal of another mesostructure says it."""
    grains: str
    """How a message names the grains."""
    measure: Callable[[Sequence[AnalyticalState], Sequence[np.ndarray]], np.ndarray]
    """(planes, each plane's hexagon area [m^2], shape (n_cells,)) -> V_cell [m^2 or m^3], shape (n_cells,)."""

    @property
    def n_planes(self) -> int:
        """Number of planes: one per lateral axis."""
        return len(self.dimension.frame) - 1


NARROW_FROM_CELLS = 8192
"""Batches of at least this many cells go on with their unconverged cells alone once half have converged
(``AnalyticalCell._narrowed``); smaller ones iterate whole, where gathering costs more than it saves (a speed
setting: the same bits)."""

LAYOUTS = {
    2: CellLayout(dimension(2), lambda plane: plane, lambda state: (state,), ("",), ("",), hcell.plain_alpha0,
                  "the plain H-cell only (six equal touching grains)", "grains", _hexagon_area),
    3: CellLayout(dimension(3), Analytical3DState, tuple, ("a_", "b_"), ("_a", "_b"), hcell.plain_alpha0_3d,
                  "the plain ten-sphere H-cell only in 3D (equal touching spheres, planes 90 deg apart)", "spheres",
                  _polyhedron_volume),
}
"""The closed form's cell of each dimension: the planar H-cell (one plane; its state is the plane's) and the
ten-sphere cell (``Analytical3DState``)."""
PLANE_OBSERVABLES = ("alpha_deg", "d1", "d2", "N1", "N2", "T1", "closed1", "closed2")
"""Per-plane quantities of ``observables``."""


def plain_cell_alpha0(meso: Mesostructure, layout: CellLayout) -> float:
    """Opening angle alpha0 [deg] of ``meso`` if it is the plain cell of ``layout``; ValueError (one line) for a
    cell of another dimension (saying which backend to build) or another cell."""
    if meso.dim != layout.dimension.dim:
        raise ValueError(f"mesostructure {meso.name!r} is a {meso.dim}D cell and this analytical backend models "
                         f"{layout.dimension.dim}D cells: build the backend with make_cell_model('analytical', "
                         f"dim={meso.dim}) (dim = the mesostructure's dim)")
    plain = layout.plain_alpha0(meso)
    if plain is None:
        raise ValueError(f"analytical models {layout.models}; mesostructure {meso.name!r} is not one: use --backend "
                         f"dem or ann")
    return plain[0]


def cell_alpha0(mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int,
                check: Callable[[Mesostructure], float], radius: float, grains: str) -> np.ndarray:
    """Opening angle alpha0 [deg] of each of ``n_cells`` cells, shape (n_cells,), from one
    mesostructure or one per cell.

    Raises:
        ValueError: (one line) a mesostructure that ``check`` (the backend's
            ``check_mesostructure``, which returns alpha0) refuses, or whose ``grains`` have
            another radius than the backend's ``radius`` [m].
    """
    distinct, index = per_cell(mesostructure, n_cells)
    alpha0_deg = np.array([check(meso) for meso in distinct])[index]
    for meso in distinct:
        if not np.allclose(meso.radius, radius, rtol=1e-12, atol=0.0):
            raise ValueError(f"mesostructure {meso.name!r} has {grains} of radius {meso.radius[0]:g} m, the "
                             f"analytical cell {radius:g} m (--radius)")
    return alpha0_deg


class AnalyticalCell:
    """Closed-form H-cell of ``dim`` dimensions (module docstring), vectorised over cells.

    Args:
        contact_law: contact stiffnesses and friction (a law of ``warp_hcell.core.parameters.CONTACT_LAWS``).
        radius: grain radius r [m].
        g2: coefficient of the published "G2" variant of the equilibrium (spec section 5),
            N2 = N1 cos a + T1 sin a + g2 T1 [-]. 0 (the default) is the consistent model.
        tolerance: equilibrium residual accepted, as a fraction of kn r [-] (Hertz-Mindlin: kn is
            the tangent stiffness at an overlap of HERTZ_DT_OVERLAP D).
        max_iterations: Newton/bisection iterations allowed per increment [-]; cells still
            above the tolerance are counted in ``diagnostics["n_unconverged"]``.

    ``step`` reports ``diagnostics``, summed over the planes: ``iterations`` (residual evaluations of the
    batch), ``n_unconverged`` (cells above the tolerance), ``n_alpha_limit`` (cells held at alpha = 90 deg)
    and, with several planes, ``n_cross_plane``.
    """

    name = "analytical"
    dim = 2
    """Spatial dimension of the cells (``LAYOUTS``); ``Analytical3DCell`` has 3."""

    def __init__(
        self,
        contact_law: Law,
        radius: float,
        *,
        g2: float = 0.0,
        tolerance: float = 1e-10,
        max_iterations: int = 60,
    ) -> None:
        self.layout = LAYOUTS[self.dim]
        self.contact_law = contact_law
        self.radius = check_positive("radius", radius)
        if not math.isfinite(g2):
            raise ValueError(f"g2 = {g2:g} must be finite")
        self.g2 = float(g2)
        self.diameter = 2.0 * self.radius
        self.law: PairLaw = pair_law(contact_law, self.radius, self.radius)
        """The contact law of the cell's equal grains (numpy)."""
        self.kn = self.law.kn
        """Linear: kn [N/m]; Hertz-Mindlin: kh [N/m^1.5]."""
        self.kt = self.law.kt
        """Linear: kt [N/m]; Hertz-Mindlin: ks [N/m^1.5]."""
        self.mu = contact_law.mu
        self.tolerance = check_positive("tolerance", tolerance)
        self.f_tolerance = self.tolerance * self.stiffness_scale * self.radius
        if int(max_iterations) < 1:
            raise ValueError(f"max_iterations = {max_iterations} must be >= 1")
        self.max_iterations = int(max_iterations)
        self.cell_alpha0_deg: np.ndarray | None = None
        """Per-cell initial opening angles [deg] of ``with_cell_laws``; None: the mesostructure's."""

    @property
    def hertz(self) -> bool:
        """True for the Hertz-Mindlin law."""
        return not self.law.linear

    @property
    def stiffness_scale(self):
        """A normal stiffness [N/m] of the cell's contacts for tolerances and Newton safeguards: kn;
        Hertz-Mindlin: the tangent stiffness 1.5 kh sqrt(delta) at delta = HERTZ_DT_OVERLAP D."""
        if self.law.linear:
            return self.kn
        return self.law.normal_stiffness(HERTZ_DT_OVERLAP * self.diameter)

    def _pathological(self, overlap: np.ndarray) -> np.ndarray:
        """Normal force [N] of the pathological contacts at ``overlap`` [m] (never tension)."""
        return self.law.normal(overlap)

    @classmethod
    def with_cell_laws(cls, kn: np.ndarray, kt_over_kn: np.ndarray, phi_g_deg: np.ndarray, radius: float,
                       alpha0_deg: np.ndarray | None = None, **options) -> AnalyticalCell:
        """A backend whose cell i has its own contact law: a population of parameter sets as one batch.

        Args:
            kn: normal contact stiffness [N/m] of each cell, shape (n_cells,), > 0.
            kt_over_kn: tangential to normal stiffness ratio [-], shape (n_cells,), > 0.
            phi_g_deg: inter-granular friction angle [deg], shape (n_cells,), in [0, 90).
            radius: grain radius r [m], shared by every cell.
            alpha0_deg: initial opening angle of each cell [deg], shape (n_cells,), in [30, 90);
                the mesostructure then fixes only topology and radius. None: its alpha0.
            options: ``g2``, ``tolerance``, ``max_iterations`` as for the constructor.

        Every batch it steps has these n_cells, in this order; ``contact_law`` is None. A cell
        gives the same result as a one-cell backend built from the same values.

        Raises:
            ValueError: (one line) a value outside the ranges of ``ContactLaw``.
        """
        kn, ratio, phi = np.broadcast_arrays(*(np.array(v, dtype=np.float64, ndmin=1)
                                               for v in (kn, kt_over_kn, phi_g_deg)))
        for name, values in (("kn", kn), ("kt_over_kn", ratio)):
            bad = ~(np.isfinite(values) & (values > 0.0))
            if bad.any():
                check_positive(name, values[bad][0])
        bad = ~((phi >= 0.0) & (phi < 90.0))
        if bad.any():
            raise ValueError(f"phi_g = {phi[bad][0]:g} deg is outside [0, 90) deg")
        model = cls(ContactLaw(), radius, **options)
        model.kn = kn.copy()
        model.kt = ratio * kn
        model._set_cell_laws(PairLaw("linear", model.kn, model.kt), phi, alpha0_deg)
        return model

    @classmethod
    def with_hertz_cell_laws(cls, shear_modulus: np.ndarray, poisson: np.ndarray, phi_g_deg: np.ndarray,
                             radius: float, alpha0_deg: np.ndarray | None = None, **options) -> AnalyticalCell:
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
        root = reduced_radius_root(model.radius, model.radius)
        law = PairLaw("hertz-mindlin", hertz_normal_modulus(G, nu) * root, hertz_shear_stiffness_modulus(G, nu) * root)
        model.kn, model.kt = law.kn, law.kt
        model._set_cell_laws(law, phi, alpha0_deg)
        return model

    def _set_cell_laws(self, law: PairLaw, phi_g_deg: np.ndarray, alpha0_deg: np.ndarray | None) -> None:
        """Per-cell ``law``, friction angles [deg] and opening angles [deg] (None: the mesostructure's)."""
        self.contact_law = None
        self.law = law
        self.mu = np.tan(np.radians(phi_g_deg))
        self.f_tolerance = self.tolerance * self.stiffness_scale * self.radius
        if alpha0_deg is not None:
            self.cell_alpha0_deg = np.array(alpha0_deg, dtype=np.float64, ndmin=1)
            hcell.touching_cells(self.cell_alpha0_deg, self.cell_alpha0_deg.size, self.diameter)  # range check

    @classmethod
    def check_mesostructure(cls, meso: Mesostructure) -> float:
        """Opening angle alpha0 [deg] of ``meso`` if it is the cell this backend models.

        Raises:
            ValueError: (one line) ``meso`` is not the plain cell of the backend's dimension: the
                touching six-equal-grain H-cell (``hcell.plain_alpha0``) or the touching ten-equal-sphere
                cell of orthogonal planes (``hcell.plain_alpha0_3d``).
        """
        return plain_cell_alpha0(meso, LAYOUTS[cls.dim])

    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int):
        """Touching, force-free cells (d1 = d2 = D in every plane) at the opening angle alpha0 of each cell's
        mesostructure, or at the per-cell angles of ``with_cell_laws``.

        Args:
            mesostructure: the plain cell of the backend's dimension with this backend's radius
                (``hcell.plain_h_cell``), or a sequence of n_cells of them.
            n_cells: number of cells.

        Raises:
            ValueError: (one line) a mesostructure that is not such a cell (``check_mesostructure``)
                or whose grains have another radius.
        """
        alpha0_deg = cell_alpha0(mesostructure, n_cells, self.check_mesostructure, self.radius, self.layout.grains)
        if self.cell_alpha0_deg is not None:
            alpha0_deg = np.broadcast_to(self.cell_alpha0_deg, (int(n_cells),))
        return self.touching_state(alpha0_deg, n_cells)

    def touching_state(self, alpha0_deg: float | np.ndarray, n_cells: int):
        """Touching, force-free cells at opening angle(s) ``alpha0_deg`` [deg] (scalar or (n_cells,))."""
        return self.layout.state(*(self.touching_plane(alpha0_deg, n_cells) for _ in range(self.layout.n_planes)))

    def touching_plane(self, alpha0_deg: float | np.ndarray, n_cells: int) -> AnalyticalState:
        """One plane of touching, force-free cells at opening angle(s) ``alpha0_deg`` [deg]."""
        alpha, l1, l2 = hcell.touching_cells(alpha0_deg, n_cells, self.diameter)
        D = np.full(alpha.shape, self.diameter)
        zero = np.zeros_like(alpha)
        return AnalyticalState(l1, l2, 0.5 * D, D, alpha, zero, zero.copy(), zero.copy())

    def step(self, state, d_eps_local: np.ndarray, *, with_tangent: bool = False) -> tuple[Any, CellResponse]:
        """Advance every cell by its local strain increment; ``state`` is left untouched.

        Args:
            state: cells at the start of the increment.
            d_eps_local: (d_eps_n, d_eps_t) or (d_eps_n, d_eps_t1, d_eps_t2) [-], shape (n_cells, dim),
                compression positive.
            with_tangent: also return the consistent tangent d(S_nn, S_tktk)/d(d_eps_n, d_eps_tk) [N m],
                shape (n_cells, dim, dim), in ``CellResponse.tangent``.

        Returns:
            The equilibrium state at the end of the increment and its response: moment [N m], shape
            (n_cells, dim, dim), local frame, compression positive; V_cell (``area``) [m^2 or m^3].
        """
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        old = self.layout.planes(state)
        steps = [self.plane_step(plane, d_eps[:, [0, k]], with_tangent=with_tangent) for k, plane in enumerate(old, 1)]
        planes = [new for new, _ in steps]
        responses = [response for _, response in steps]
        new = self.layout.state(*planes)
        moment = self._moment(planes, [r.moment for r in responses])
        tangent = self._cell_tangent(old, planes, [r.tangent for r in responses]) if with_tangent else None
        diagnostics = {key: sum(r.diagnostics[key] for r in responses) for key in responses[0].diagnostics}
        if len(planes) > 1:  # planes that may meet
            diagnostics["n_cross_plane"] = float(np.count_nonzero(self.cross_plane_contact(new)))
        return new, CellResponse(moment, self.layout.measure(planes, [r.area for r in responses]), diagnostics, tangent)

    def plane_step(self, plane: AnalyticalState, d_eps_local: np.ndarray, *,
                   with_tangent: bool = False) -> tuple[AnalyticalState, CellResponse]:
        """Advance one plane by (d_eps_n, d_eps_t) [-], shape (n_cells, 2); ``plane`` is left untouched.

        Returns its equilibrium state and its response: moment (n_cells, 2, 2) [N m] and hexagon area [m^2];
        ``tangent`` (n_cells, 2, 2) d(S_nn, S_tt)/d(d_eps_n, d_eps_t) [N m] when asked.
        """
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        l1 = plane.l1 * (1.0 - d_eps[:, 0])
        l2 = plane.l2 * (1.0 - d_eps[:, 1])
        new, diagnostics = self._solve(plane, l1, l2)
        moment, area = self.plane_response(new)
        tangent = self._tangent(plane, new) if with_tangent else None
        return new, CellResponse(moment, area, diagnostics, tangent)

    def plane_response(self, plane: AnalyticalState) -> tuple[np.ndarray, np.ndarray]:
        """Love-Weber moment (n_cells, 2, 2) [N m] and hexagon area (n_cells,) [m^2] of one plane."""
        return hcell.love_weber_moment(plane.alpha, plane.N1, plane.N2, plane.T1, plane.l1, plane.l2, kn=self.kn,
                                       diameter=self.diameter, normal=self._pathological if self.hertz else None)

    def _axial_moment(self, l1: np.ndarray) -> np.ndarray:
        """kn <D - l1> l1 [N m] (the law's force at overlap D - l1, times l1): the contact 1-4 that every plane
        adds to S_nn."""
        if self.hertz:
            return self.law.normal(self.diameter - l1) * l1
        return self.kn * np.maximum(self.diameter - l1, 0.0) * l1

    def _axial_slope(self, old_l1: np.ndarray, l1: np.ndarray) -> np.ndarray:
        """d(kn <D - l1> l1)/d(d_eps_n) [N m] at the end of an increment that started at ``old_l1``."""
        if self.hertz:
            overlap = self.diameter - l1
            slope = self.law.normal(overlap) - self.law.normal_stiffness(overlap) * l1
        else:
            slope = self.kn * (self.diameter - 2.0 * l1)
        return np.where(self.diameter - l1 > 0.0, slope, 0.0) * -old_l1

    @staticmethod
    def _once(values: Sequence[np.ndarray], shared: Callable[[], np.ndarray]) -> np.ndarray:
        """The sum of the planes' ``values`` with the axial contact's ``shared()`` term, which each counts,
        counted once."""
        total = values[0]
        for value in values[1:]:
            total = total + value - shared()
        return total

    def _moment(self, planes: Sequence[AnalyticalState], moments: Sequence[np.ndarray]) -> np.ndarray:
        """The cell's moment (n_cells, dim, dim) [N m] from its planes' (n_cells, 2, 2)."""
        moment = np.zeros((moments[0].shape[0], self.dim, self.dim))
        moment[:, 0, 0] = self._once([m[:, 0, 0] for m in moments], lambda: self._axial_moment(planes[0].l1))
        for k, plane_moment in enumerate(moments, 1):
            moment[:, k, k] = plane_moment[:, 1, 1]
        return moment

    def _cell_tangent(self, old: Sequence[AnalyticalState], new: Sequence[AnalyticalState],
                      tangents: Sequence[np.ndarray]) -> np.ndarray:
        """The cell's tangent (n_cells, dim, dim) [N m] from its planes' (n_cells, 2, 2)."""
        tangent = np.zeros((tangents[0].shape[0], self.dim, self.dim))
        tangent[:, 0, 0] = self._once([t[:, 0, 0] for t in tangents], lambda: self._axial_slope(old[0].l1, new[0].l1))
        for k, plane_tangent in enumerate(tangents, 1):
            tangent[:, 0, k], tangent[:, k, 0] = plane_tangent[:, 0, 1], plane_tangent[:, 1, 0]
            tangent[:, k, k] = plane_tangent[:, 1, 1]
        return tangent

    def _regime(self, old: AnalyticalState, new: AnalyticalState) -> dict[str, np.ndarray]:
        """Contact regime reached by the solve, as the masks that ``_partials`` holds fixed."""
        D = self.diameter
        d_alpha = new.alpha - old.alpha
        if self.hertz:
            d1_mid = 0.5 * (old.d1 + new.d1)
            trial = old.T1 + self.law.move_stiffness(D - old.d1, D - new.d1) * d1_mid * d_alpha
        else:
            trial = old.T1 + self.kt * 0.5 * (old.d1 + new.d1) * d_alpha
        cap = self.mu * new.N1
        return {
            "closed1": (D - new.d1 > 0.0).astype(np.float64),
            "closed2": (D - 2.0 * new.y2 > 0.0).astype(np.float64),
            "stick": np.abs(trial) < cap,
            "slide_sign": np.copysign(1.0, trial),
            "touch14": (D - new.l1 > 0.0).astype(np.float64),
            "touch26": (D - new.l2 > 0.0).astype(np.float64),
        }

    def _partials(self, old: AnalyticalState, new: AnalyticalState, regime: dict[str, np.ndarray]):
        """Partial derivatives of f and (S_nn, S_tt) with respect to (y2, l1, l2) in a fixed regime.

        Same expressions as ``_solve`` and ``hcell.love_weber_moment`` with every max/clip
        replaced by the branch of ``regime``. Everything but N2 and the pathological contacts
        depends on (y2, l1) through u = l1/2 - y2 and on l2 through h = l2/2; with d1 = |(u, h)|,
        c = u/d1, s = h/d1, alpha = atan2(h, u): dd1 = c du + s dh, dc = s (s du - c dh)/d1,
        ds = c (c dh - s du)/d1, dalpha = (c dh - s du)/d1.

        Returns:
            (f_x, S_x): shapes (n_cells, 3) and (n_cells, 2, 3), columns d/dy2, d/dl1, d/dl2.
        """
        kn, kt, mu, D = self.kn, self.kt, self.mu, self.diameter
        y2, l1, l2 = new.y2, new.l1, new.l2
        u, h = 0.5 * l1 - y2, 0.5 * l2
        d1 = np.hypot(h, u)
        c, s = u / d1, h / d1
        cs_d1 = c * s / d1
        c_u, c_h = s * s / d1, -cs_d1
        s_u, s_h = -cs_d1, c * c / d1
        a_u, a_h = -s / d1, c / d1
        closed1, closed2 = regime["closed1"], regime["closed2"]
        d_alpha = new.alpha - old.alpha
        d1_mid = 0.5 * (old.d1 + d1)
        stick, slide = regime["stick"], regime["slide_sign"] * mu
        if self.hertz:
            law = self.law
            N1 = law.normal(D - d1) * closed1
            k1 = law.normal_stiffness(D - d1) * closed1
            N1_u, N1_h = -k1 * c, -k1 * s
            N2 = law.normal(D - 2.0 * y2) * closed2
            N2_y = -2.0 * law.normal_stiffness(D - 2.0 * y2) * closed2
            # kt = kt(D - d1_old, D - d1): dkt/du = -kt' c, dkt/dh = -kt' s, kt' its slope in the end overlap
            kt = law.move_stiffness(D - old.d1, D - d1)
            kt_d = -law.move_stiffness_slope(D - old.d1, D - d1)
            T1 = np.where(stick, old.T1 + kt * d1_mid * d_alpha, slide * N1)
            T_u = np.where(stick, kt * (0.5 * c * d_alpha + d1_mid * a_u) + kt_d * c * d1_mid * d_alpha, slide * N1_u)
            T_h = np.where(stick, kt * (0.5 * s * d_alpha + d1_mid * a_h) + kt_d * s * d1_mid * d_alpha, slide * N1_h)
        else:
            N1 = kn * (D - d1) * closed1
            N1_u, N1_h = -kn * closed1 * c, -kn * closed1 * s
            N2 = kn * (D - 2.0 * y2) * closed2
            N2_y = -2.0 * kn * closed2
            T1 = np.where(stick, old.T1 + kt * d1_mid * d_alpha, slide * N1)
            T_u = np.where(stick, kt * (0.5 * c * d_alpha + d1_mid * a_u), slide * N1_u)
            T_h = np.where(stick, kt * (0.5 * s * d_alpha + d1_mid * a_h), slide * N1_h)
        sg = s + self.g2
        f_u = -N1_u * c - N1 * c_u - s_u * T1 - sg * T_u
        f_h = -N1_h * c - N1 * c_h - s_h * T1 - sg * T_h
        # S_nn = 4 u A + 4 N2 y2 + kn (D - l1) l1, S_tt = 4 h B + 2 kn (D - l2) l2
        A = N1 * c + T1 * s
        B = N1 * s - T1 * c
        A_u = N1_u * c + N1 * c_u + T_u * s + T1 * s_u
        A_h = N1_h * c + N1 * c_h + T_h * s + T1 * s_h
        B_u = N1_u * s + N1 * s_u - T_u * c - T1 * c_u
        B_h = N1_h * s + N1 * s_h - T_h * c - T1 * c_h
        Snn_u, Snn_h = 4.0 * (A + u * A_u), 4.0 * u * A_h
        Stt_u, Stt_h = 4.0 * h * B_u, 4.0 * (B + h * B_h)
        # chain rule: du/dy2 = -1, du/dl1 = dh/dl2 = 1/2
        f_x = np.stack([N2_y - f_u, 0.5 * f_u, 0.5 * f_h], axis=-1)
        # the pathological contacts: d/dl [F(D - l) l] = F(D - l) - F'(D - l) l
        if self.hertz:
            axial_l1 = (self.law.normal(D - l1) - self.law.normal_stiffness(D - l1) * l1) * regime["touch14"]
            lateral_l2 = (self.law.normal(D - l2) - self.law.normal_stiffness(D - l2) * l2) * regime["touch26"]
        else:
            axial_l1 = kn * (D - 2.0 * l1) * regime["touch14"]
            lateral_l2 = kn * (D - 2.0 * l2) * regime["touch26"]
        S_nn_x = np.stack([4.0 * (N2_y * y2 + N2) - Snn_u, 0.5 * Snn_u + axial_l1, 0.5 * Snn_h], axis=-1)
        S_tt_x = np.stack([-Stt_u, 0.5 * Stt_u, 0.5 * Stt_h + 2.0 * lateral_l2], axis=-1)
        return f_x, np.stack([S_nn_x, S_tt_x], axis=1)

    def _tangent(self, old: AnalyticalState, new: AnalyticalState) -> np.ndarray:
        """Consistent tangent d(S_nn, S_tt)/d(d_eps_n, d_eps_t) [N m], shape (n_cells, 2, 2)."""
        f_x, S_x = self._partials(old, new, self._regime(old, new))
        f_y, f_l1, f_l2 = f_x[:, 0], f_x[:, 1], f_x[:, 2]
        S_y, S_l1, S_l2 = S_x[:, :, 0], S_x[:, :, 1], S_x[:, :, 2]
        # y2 held at alpha = 90 deg (no equilibrium below): y2 = l1/2; both contacts open
        # (f identically 0): y2 kept; else implicit differentiation of f = 0.
        at_limit = (0.5 * new.l1 - new.y2 == 0.0)
        free = (f_y == 0.0) & ~at_limit
        safe = np.where(at_limit | free, 1.0, f_y)
        dy_l1 = np.where(at_limit, 0.5, np.where(free, 0.0, -f_l1 / safe))
        dy_l2 = np.where(at_limit | free, 0.0, -f_l2 / safe)
        dS_l1 = S_l1 + S_y * dy_l1[:, None]
        dS_l2 = S_l2 + S_y * dy_l2[:, None]
        # l_i = l_i,old (1 - d_eps_i)
        return np.stack([dS_l1 * -old.l1[:, None], dS_l2 * -old.l2[:, None]], axis=-1)

    def _solve(self, old: AnalyticalState, l1: np.ndarray, l2: np.ndarray,
               resume: tuple | None = None) -> tuple[AnalyticalState, dict]:
        """Equilibrium y2 for the new lengths; returns the state and the diagnostics.

        ``resume``: (y, lo, hi, walk, iteration), the iterates of a batch's unconverged cells at the start of
        that iteration (``_narrowed``); None: the first iteration from the old y2.
        """
        kn, kt, mu, D, g2 = self.kn, self.kt, self.mu, self.diameter, self.g2
        law, hertz, k_scale = self.law, self.hertz, self.stiffness_scale
        h = 0.5 * l2
        half_l1 = 0.5 * l1
        alpha_old, T_old, half_d1_old = old.alpha, old.T1, 0.5 * old.d1
        if resume is None:
            y, lo, hi, walk, first = np.minimum(old.y2, half_l1), np.zeros_like(l1), half_l1, None, 1
        else:
            y, lo, hi, walk, first = resume
        large = l1.size >= NARROW_FROM_CELLS
        for iteration in range(first, self.max_iterations + 1):
            u = half_l1 - y
            d1 = np.hypot(h, u)
            c = u / d1
            s = h / d1
            alpha = np.arctan2(h, u)
            gap1 = D - d1
            closed1 = gap1 > 0.0
            gap2 = D - 2.0 * y
            d_alpha = alpha - alpha_old
            d1_mid = half_d1_old + 0.5 * d1
            if hertz:
                N1, N2 = law.normal(gap1), law.normal(gap2)
                kt = law.move_stiffness(D - old.d1, gap1)
            else:
                N1 = kn * np.maximum(gap1, 0.0)
                N2 = kn * np.maximum(gap2, 0.0)
            trial = T_old + kt * d1_mid * d_alpha
            cap = mu * N1
            T1 = np.minimum(np.maximum(trial, -cap), cap)
            f = N2 - N1 * c - (s + g2) * T1
            converged = np.abs(f) <= self.f_tolerance
            if converged.all():
                break
            # f > 0 at y2 = l1/2 (alpha = 90 deg, grains 2-1-6 aligned): no equilibrium in
            # the admissible range; the cell stays at that limit (reported).
            converged |= (u == 0.0) & (f > 0.0)
            if iteration == self.max_iterations or converged.all():
                break
            if large and np.count_nonzero(converged) >= max(1, l1.size // 2):
                return self._narrowed(old, l1, l2, (y, lo, hi, walk, iteration), converged,
                                      (d1, alpha, N1, N2, T1, u, f))
            # Converged cells keep their y (f -> 0), so a cell's result does not depend
            # on the other cells of the batch.
            f = np.where(converged, 0.0, f)
            # df/dy2, with dd1/dy2 = -cos a, da/dy2 = sin a / d1.
            if hertz:
                # the slope of kt in the overlap is left out of the Newton slope (it only steers)
                k1, k2 = law.normal_stiffness(gap1), law.normal_stiffness(gap2)
                dT = np.where(np.abs(trial) < cap, kt * (d1_mid * s / d1 - 0.5 * c * d_alpha),
                              np.copysign(mu * k1, trial) * c * closed1)
                df = (s * (N1 * s - T1 * c) / d1 - (s + g2) * dT) - (2.0 * k2 + c * c * k1)
            else:
                dT = np.where(
                    np.abs(trial) < cap,
                    kt * (d1_mid * s / d1 - 0.5 * c * d_alpha),
                    np.copysign(mu * kn, trial) * c * closed1,
                )
                df = (s * (N1 * s - T1 * c) / d1 - (s + g2) * dT) - kn * (2.0 * (gap2 > 0.0) + c * c * closed1)
            lo = np.where(f > 0.0, y, lo)
            hi = np.where(f < 0.0, y, hi)
            # f mostly decreases in y2; a slope that is not negative (all contacts open, or a
            # friction-locked cell sliding back) is made tiny and negative, so y leaves the
            # bracket and the walk below takes over.
            y_newton = y - f / np.minimum(df, -k_scale * 1e-12)
            # Newton inside the open bracket, or a step below the resolution of y.
            inside = ((y_newton > lo) & (y_newton < hi)) | (y_newton == y)
            if inside.all():
                y = y_newton
                continue
            # Else (Newton cycles across the kinks where contacts open, or f grows with y
            # where a friction-locked cell slides back): walk towards the root by steps
            # that start at the size of the increment and double, never beyond the middle
            # of the bracket, so the (wide) initial bracket costs no long bisection; the
            # walk may reach the limit y2 = l1/2 while that end is not yet evaluated.
            if walk is None:
                walk = np.abs(l1 - old.l1) + np.abs(l2 - old.l2) + self.f_tolerance / k_scale
            mid = 0.5 * (lo + hi)
            upper = np.where(hi == half_l1, hi, mid)
            y_walk = np.where(f > 0.0, np.minimum(y + walk, upper), np.maximum(y - walk, mid))
            y = np.where(inside, y_newton, y_walk)
            walk = np.where(inside, walk, 2.0 * walk)
        n_limit = np.count_nonzero((u == 0.0) & (f > self.f_tolerance))
        diagnostics = {
            "iterations": float(iteration),
            "n_unconverged": float(np.count_nonzero(np.abs(f) > self.f_tolerance) - n_limit),
            "n_alpha_limit": float(n_limit),
        }
        return AnalyticalState(l1, l2, y, d1, alpha, N1, N2, T1), diagnostics

    def _narrowed(self, old: AnalyticalState, l1: np.ndarray, l2: np.ndarray, iterates: tuple, done: np.ndarray,
                  values: tuple) -> tuple[AnalyticalState, dict]:
        """``_solve``'s result when the cells ``done`` have converged at the start of an iteration: theirs are
        their ``values`` (d1, alpha, N1, N2, T1, u, f) at their y2 (``iterates``: y, lo, hi, walk, iteration),
        the bits that evaluating them again at that y2 would give; the others' go on in a batch of their own
        (``_solve``'s ``resume``, with their per-cell constants). A cell's result does not depend on its batch."""
        keep = np.flatnonzero(~done)
        part = copy.copy(self)
        for name in ("kn", "kt", "mu", "f_tolerance"):
            setattr(part, name, _cells_of(getattr(self, name), keep, l1.size))
        part.law = PairLaw(self.law.name, _cells_of(self.law.kn, keep, l1.size), _cells_of(self.law.kt, keep, l1.size))
        y, lo, hi, walk, iteration = iterates
        new, diagnostics = part._solve(AnalyticalState(*(field[keep] for field in old)), l1[keep], l2[keep],
                                       (y[keep], lo[keep], hi[keep], None if walk is None else walk[keep], iteration))
        d1, alpha, N1, N2, T1, u, f = values  # this iteration's arrays, written over at the cells kept
        for full, narrow in zip((y, d1, alpha, N1, N2, T1), (new.y2, new.d1, new.alpha, new.N1, new.N2, new.T1)):
            full[keep] = narrow
        n_limit = np.count_nonzero(done & (u == 0.0) & (f > self.f_tolerance))
        diagnostics["n_unconverged"] += float(np.count_nonzero(done & (np.abs(f) > self.f_tolerance)) - n_limit)
        diagnostics["n_alpha_limit"] += float(n_limit)
        return AnalyticalState(l1, l2, y, d1, alpha, N1, N2, T1), diagnostics

    def response(self, state) -> CellResponse:
        """Meso-stress of ``state`` without advancing it: moment (n_cells, dim, dim) [N m], V_cell (``area``)."""
        planes = self.layout.planes(state)
        responses = [self.plane_response(plane) for plane in planes]
        moment = self._moment(planes, [m for m, _ in responses])
        return CellResponse(moment, self.layout.measure(planes, [a for _, a in responses]))

    def volume(self, state) -> np.ndarray:
        """V_cell [m^2 or m^3] of every cell, shape (n_cells,): the hexagon or the polyhedron through the centres."""
        return self.response(state).area

    def positions(self, state) -> np.ndarray:
        """Grain centres (n_cells, n_grains, dim) [m] in the local frame, cell centre at the origin
        (``cell_positions``)."""
        return cell_positions(self.layout.planes(state))

    def cross_plane_contact(self, state) -> np.ndarray:
        """bool (n_cells,): a lateral grain of one plane within one diameter of a lateral grain of another
        (planes at right angles); never with one plane."""
        planes = self.layout.planes(state)
        meet = np.zeros(planes[0].l1.shape, dtype=bool)
        for a, b in combinations(planes, 2):
            meet |= (a.y2 - b.y2) ** 2 + 0.25 * (a.l2 ** 2 + b.l2 ** 2) < self.diameter ** 2
        return meet

    def observables(self, state) -> dict[str, np.ndarray]:
        """Named per-cell quantities, each shape (n_cells,).

        ``l1`` and each plane's lateral length ``l2`` (``l3``) [m]; per plane, with its suffix (none for
        one plane, ``_a`` / ``_b`` for two), ``alpha_deg`` [deg], ``d1, d2`` [m], ``N1, N2, T1`` [N]
        (compression positive, T1 > 0 resists opening), ``closed1, closed2`` (bool: the contacts carry
        force); ``S_nn, S_tt`` (``S_nn, S_t1t1, S_t2t2``) [N m]; ``area`` [m^2] (``volume`` [m^3]);
        ``cross_plane`` (bool) with several planes; grain centres ``x_n{i}, x_t{i}`` (``x_n{i}, x_t1{i},
        x_t2{i}``) [m] for labels i (cell centre at the origin).
        """
        planes = self.layout.planes(state)
        response = self.response(state)
        out: dict[str, np.ndarray] = {"l1": planes[0].l1}
        out.update({f"l{k}": plane.l2 for k, plane in enumerate(planes, 2)})
        for suffix, plane in zip(self.layout.suffixes, planes):
            values = (np.degrees(plane.alpha), plane.d1, 2.0 * plane.y2, plane.N1, plane.N2, plane.T1,
                      plane.N1 > 0.0, plane.N2 > 0.0)
            out.update({f"{key}{suffix}": value for key, value in zip(PLANE_OBSERVABLES, values)})
        frame = self.layout.dimension.frame
        out.update({f"S_{axis}{axis}": response.moment[:, i, i] for i, axis in enumerate(frame)})
        out[self.layout.dimension.measure] = response.area
        if len(planes) > 1:  # planes that may meet
            out["cross_plane"] = self.cross_plane_contact(state)
        x = cell_positions(planes)
        for g in range(x.shape[1]):
            for i, axis in enumerate(frame):
                out[f"x_{axis}{g + 1}"] = x[:, g, i]
        return out

    def take(self, state, index: np.ndarray):
        """Cells ``state[index]`` (int array, repetition allowed)."""
        index = np.asarray(index, dtype=np.intp)
        return self.layout.state(*(AnalyticalState(*(value[index] for value in plane))
                                   for plane in self.layout.planes(state)))

    def state_to_arrays(self, state) -> dict[str, np.ndarray]:
        """Copies of the planes' fields, keyed by field name with each plane's prefix (none for one plane,
        ``a_`` / ``b_`` for two)."""
        return {f"{prefix}{key}": np.array(value, dtype=np.float64)
                for prefix, plane in zip(self.layout.prefixes, self.layout.planes(state))
                for key, value in zip(AnalyticalState._fields, plane)}

    def state_from_arrays(self, arrays: Mapping[str, Any]):
        """Inverse of ``state_to_arrays``; KeyError names a missing field."""
        return self.layout.state(*(AnalyticalState(*(np.array(arrays[f"{prefix}{key}"], dtype=np.float64)
                                                     for key in AnalyticalState._fields))
                                   for prefix in self.layout.prefixes))


class Analytical3DCell(AnalyticalCell):
    """The closed form of the ten-sphere cell: ``AnalyticalCell`` of two planes (``dim`` = 3)."""

    dim = 3
