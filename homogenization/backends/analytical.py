"""Analytical H-cell backend: the one-unknown equilibrium solve of spec section 6.

``AnalyticalCell`` implements ``warp_hcell.core.contract.CellModel``. Per increment and
per cell, l1 and l2 follow the imposed local strain (spec section 3); the only unknown,
y2 = d2/2, is found such that grain 2 is in equilibrium along n:

    f(y2) = N2 - N1 cos a - T1 sin a (- g2 T1) = 0,

with N1 = kn <D - d1>, N2 = kn <D - d2> and T1 the incremental tangential spring with a
Coulomb cap evaluated from the state at the start of the increment:
T_trial = T1_old + kt d1_mid (a - a_old), T1 = clip(T_trial, -mu N1, +mu N1). The cap
takes its sign from the trial force, and T1 = 0 (history reset) whenever the type-1
contact is open, because then N1 = 0. The solve is a safeguarded Newton iteration on the
whole batch at once, from the previous y2, inside a bracket in (0, l1/2]: when a Newton step
leaves the bracket (kinks where contacts open or start sliding), y2 walks towards the root
by doubling steps, never past the middle of the bracket. Converged cells are frozen, so a
cell's result does not depend on its batch. Where both contacts are open f is identically
zero and y2 is kept. Where f > 0 even at y2 = l1/2 (alpha = 90 deg) the cell is held there.

With ``with_tangent=True`` the step also returns the consistent tangent
d(S_nn, S_tt)/d(d_eps_n, d_eps_t) of the increment, by implicit differentiation of
f(y2; l1, l2) = 0 in the regime the solve reached (which contacts are closed, stick or slide
of the type-1 contacts with the sign of the trial force, pathological contacts):
dy2/dl = -(df/dl) / (df/dy2), dS/dl = dS/dl|_y2 + dS/dy2 dy2/dl, and dl_i/d(d_eps_i) = -l_i,old.
The partial derivatives of the frozen-regime residual and moment are written out in
``_partials``.

The Hertz-Mindlin law (``warp_hcell.core.parameters.HertzMindlinLaw``, used by the ten-sphere
cell of ``analytical3d``, whose planes are such cells of spheres) replaces kn <D - d> by
kh <D - d>^(3/2) and kt by the mean Mindlin stiffness of the increment's type-1 overlaps,
kt(D - d1_old, D - d1) (``warp_hcell.core.laws.hertz_mindlin.move_stiffness``, as the DEM's), kh and ks the pair
constants of equal spheres (R* = r / 2, ``warp_hcell.core.laws.hertz_mindlin.pair_constants``); the
solve, its bracket and the tangent are the same with the overlap-dependent slopes.

Sign convention: compression and contraction positive; T1 > 0 resists opening (alpha
growing). Local frame: index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import numpy as np

from warp_hcell.mesostructures import hcell
from warp_hcell.core.contract import ArrayStateMixin, CellResponse
from warp_hcell.mesostructures.mesostructure import Mesostructure, per_cell
from warp_hcell.core.contact import PairLaw, pair_law
from warp_hcell.core.parameters import HERTZ_DT_OVERLAP, check_positive, ContactLaw, Law


class AnalyticalState(NamedTuple):
    """Batch of analytical H-cells; every field has shape (n_cells,).

    (l1, l2, y2) fix the geometry; the other fields are derived from it at the end of the
    increment that produced the state and kept so that the next increment starts from them.
    """

    l1: np.ndarray
    """Axial length, centre 1 to centre 4 [m]."""
    l2: np.ndarray
    """Distance between the lateral columns [m]."""
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


def plain_cell_alpha0(meso: Mesostructure, plain_alpha0: Callable[[Mesostructure], tuple[float, ...] | None],
                      models: str, dim: int) -> float:
    """Opening angle alpha0 [deg] of ``meso`` as ``plain_alpha0`` (``hcell.plain_alpha0`` or
    ``hcell.plain_alpha0_3d``) reads it; ValueError (one line) for a cell of another dimension
    than the backend's ``dim`` (saying which backend to build), or naming what the backend
    ``models`` where ``plain_alpha0`` reads none."""
    if meso.dim != dim:
        raise ValueError(f"mesostructure {meso.name!r} is a {meso.dim}D cell and this analytical backend models "
                         f"{dim}D cells: build the backend with make_cell_model('analytical', dim={meso.dim}) "
                         f"(dim = the mesostructure's dim)")
    plain = plain_alpha0(meso)
    if plain is None:
        raise ValueError(f"analytical models {models}; mesostructure {meso.name!r} is not one: use --backend dem or ann")
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


class AnalyticalCell(ArrayStateMixin):
    """Closed-form H-cell (spec sections 2-7), vectorised over cells.

    Args:
        contact_law: contact stiffnesses and friction (a law of ``warp_hcell.core.parameters.CONTACT_LAWS``;
            the Hertz-Mindlin law as the plane of the ten-sphere cell, ``analytical3d``).
        radius: grain radius r [m].
        g2: coefficient of the published "G2" variant of the equilibrium (spec section 5),
            N2 = N1 cos a + T1 sin a + g2 T1 [-]. 0 (the default) is the consistent model.
        tolerance: equilibrium residual accepted, as a fraction of kn r [-] (Hertz-Mindlin: kn is
            the tangent stiffness at an overlap of HERTZ_DT_OVERLAP D).
        max_iterations: Newton/bisection iterations allowed per increment [-]; cells still
            above the tolerance are counted in ``diagnostics["n_unconverged"]``.

    ``step`` reports ``diagnostics``: ``iterations`` (residual evaluations of the batch),
    ``n_unconverged`` (cells above the tolerance) and ``n_alpha_limit`` (cells held at
    alpha = 90 deg, where no equilibrium exists below it).
    """

    name = "analytical"
    state_type = AnalyticalState

    def __init__(
        self,
        contact_law: Law,
        radius: float,
        *,
        g2: float = 0.0,
        tolerance: float = 1e-10,
        max_iterations: int = 60,
    ) -> None:
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
        model.contact_law = None
        model.kn = kn.copy()
        model.kt = ratio * kn
        model.law = PairLaw("linear", model.kn, model.kt)
        model.mu = np.tan(np.radians(phi))
        model.f_tolerance = model.tolerance * model.kn * model.radius
        if alpha0_deg is not None:
            model.cell_alpha0_deg = np.array(alpha0_deg, dtype=np.float64, ndmin=1)
            hcell.touching_cells(model.cell_alpha0_deg, model.cell_alpha0_deg.size, model.diameter)  # range check
        return model

    @staticmethod
    def check_mesostructure(meso: Mesostructure) -> float:
        """Opening angle alpha0 [deg] of ``meso`` if it is the cell this backend models.

        Raises:
            ValueError: (one line) ``meso`` is not the touching six-equal-grain H-cell of
                ``warp_hcell.mesostructures.hcell.h_cell`` (``hcell.plain_alpha0``).
        """
        return plain_cell_alpha0(meso, hcell.plain_alpha0, "the plain H-cell only (six equal touching grains)", 2)

    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int) -> AnalyticalState:
        """Touching, force-free cells: d1 = d2 = D at the opening angle alpha0 of each cell's mesostructure.

        Args:
            mesostructure: the plain H-cell (``warp_hcell.mesostructures.hcell.h_cell(alpha0_deg, radius)``
                with this backend's radius), or a sequence of n_cells of them.
            n_cells: number of cells.

        Raises:
            ValueError: (one line) a mesostructure that is not such an H-cell
                (``check_mesostructure``) or whose grains have another radius.
        """
        alpha0_deg = cell_alpha0(mesostructure, n_cells, self.check_mesostructure, self.radius, "grains")
        if self.cell_alpha0_deg is not None:
            alpha0_deg = np.broadcast_to(self.cell_alpha0_deg, (int(n_cells),))
        return self.touching_state(alpha0_deg, n_cells)

    def touching_state(self, alpha0_deg: float | np.ndarray, n_cells: int) -> AnalyticalState:
        """Touching, force-free cells at opening angle(s) ``alpha0_deg`` [deg] (scalar or (n_cells,))."""
        alpha, l1, l2 = hcell.touching_cells(alpha0_deg, n_cells, self.diameter)
        D = np.full(alpha.shape, self.diameter)
        zero = np.zeros_like(alpha)
        return AnalyticalState(l1, l2, 0.5 * D, D, alpha, zero, zero.copy(), zero.copy())

    def step(self, state: AnalyticalState, d_eps_local: np.ndarray, *,
             with_tangent: bool = False) -> tuple[AnalyticalState, CellResponse]:
        """Advance every cell by its local strain increment; ``state`` is left untouched.

        Args:
            state: cells at the start of the increment.
            d_eps_local: (d_eps_n, d_eps_t) [-], shape (n_cells, 2), compression positive.
            with_tangent: also return the consistent tangent d(S_nn, S_tt)/d(d_eps_n, d_eps_t)
                [N m], shape (n_cells, 2, 2), in ``CellResponse.tangent``.

        Returns:
            The equilibrium state at the end of the increment and its response.
        """
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        l1 = state.l1 * (1.0 - d_eps[:, 0])
        l2 = state.l2 * (1.0 - d_eps[:, 1])
        new, diagnostics = self._solve(state, l1, l2)
        moment, area = hcell.love_weber_moment(
            new.alpha, new.N1, new.N2, new.T1, l1, l2, kn=self.kn, diameter=self.diameter,
            normal=self._pathological if self.hertz else None
        )
        tangent = self._tangent(state, new) if with_tangent else None
        return new, CellResponse(moment, area, diagnostics, tangent)

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

    def _solve(self, old: AnalyticalState, l1: np.ndarray, l2: np.ndarray) -> tuple[AnalyticalState, dict]:
        """Equilibrium y2 for the new lengths; returns the state and the diagnostics."""
        kn, kt, mu, D, g2 = self.kn, self.kt, self.mu, self.diameter, self.g2
        law, hertz, k_scale = self.law, self.hertz, self.stiffness_scale
        h = 0.5 * l2
        half_l1 = 0.5 * l1
        alpha_old, T_old, half_d1_old = old.alpha, old.T1, 0.5 * old.d1
        lo = np.zeros_like(l1)
        hi = half_l1
        y = np.minimum(old.y2, half_l1)
        walk = None
        for iteration in range(1, self.max_iterations + 1):
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

    def response(self, state: AnalyticalState) -> CellResponse:
        """Meso-stress of ``state`` without advancing it."""
        moment, area = hcell.love_weber_moment(
            state.alpha, state.N1, state.N2, state.T1, state.l1, state.l2, kn=self.kn, diameter=self.diameter,
            normal=self._pathological if self.hertz else None
        )
        return CellResponse(moment, area)

    def observables(self, state: AnalyticalState) -> dict[str, np.ndarray]:
        """Named per-cell quantities, each shape (n_cells,).

        ``l1, l2, d1, d2`` [m], ``alpha_deg`` [deg], ``N1, N2, T1`` [N] (compression
        positive, T1 > 0 resists opening), ``S_nn, S_tt`` [N m], ``area`` [m^2],
        ``closed1, closed2`` (bool: type-1 / type-2 contacts carry force) and grain centres
        ``x_n{i}, x_t{i}`` [m] for labels i = 1..6 (cell centre at the origin).
        """
        response = self.response(state)
        return hcell.closed_form_observables(state.l1, state.l2, state.d1, 2.0 * state.y2, state.alpha, state.N1, state.N2,
                                 state.T1, response.moment, response.area)

