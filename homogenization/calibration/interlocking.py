"""Interlocking friction of a calibration's population (opt-in: ``forward.simulate(..., interlocking=...)``).

After the form of Chang & Hicher (2005, IJSS 42): the friction mobilised at the contacts of a material point
depends on its void ratio e relative to a critical one at its mean stress p,

    tan phi = (e_c(p) / e)^m tan phi_mu,    e_c(p) = e_Gamma - lambda (p / p_ref)^xi,

phi_mu the set's contact friction angle (phi_g). A point denser than e_c(p) has phi > phi_mu, which falls to
phi_mu as it dilates to e_c; a denser point at a lower pressure gets more. e = (1 + e0) J - 1, e0 the point's
void ratio where J = 1, J and p those of the accepted state; the friction is set before every increment
(explicit: each trial of an increment sees the same friction). ``InterlockingFriction`` sets it on the
population's per-cell friction (``with_cell_laws``' cells) and on a critical-state renewal's fresh cells. m, e_Gamma,
lambda, xi and s (below) may differ from point to point (per calibration set: ``FIELDS``), so one batch holds sets
of different xi.

Opt-in lag (``Interlocking.relax_strain`` gamma_r > 0): the rule reads a lagged void ratio e_r instead of e, which
follows e over distortion, d e_r = -(e_r - e) d gamma / gamma_r (exact over an increment: e_r - e scaled by
exp(-d gamma / gamma_r)), d gamma the increment's deviatoric strain (the dimension's q of the strain tensor: 3D
sqrt(3 J2), a triaxial test's abs(d eps1 - d eps3)); e_r = e at the start. e_c(p) follows p at once, so an
isotropic compression keeps the pressure dependence; in shear the interlocking decays over gamma_r of
distortion after the dilation rather than with it. With ``relax_exponent`` k the lag's strain grows with the
point's mean stress, gamma_r(p) = gamma_r (p / p_ref)^k (p of the accepted state; k = 0: gamma_r), so the decay is
spread over more distortion at a higher pressure. With ``relax_void_slope`` s it also grows with the point's initial
void ratio e0 (the test's, ``forward.simulate``), gamma_r(p, e0) = gamma_r (p / p_ref)^k exp(s (e0 - e_ref)),
e_ref = ``RELAX_VOID_REF`` (s = 0: no factor), so a looser specimen keeps its interlocking over more distortion.

Opt-in mobilisation (``Interlocking.mobilisation_strain`` a_ref > 0): the point's tan phi (the rule's, lag included)
is multiplied by r = r0 + (1 - r0) g / (a + g), g the point's accumulated distortion (the sum of its d gamma), r0 =
``mobilisation_start``, a(p, e0) = a_ref (p / p_ref)^n exp(s_m (e0 - e_ref)), n = ``mobilisation_exponent``
(default ``MOBILISATION_EXPONENT``), s_m = ``mobilisation_void_slope`` (0: no factor), p of the accepted state.

Opt-in softening since the peak (``Interlocking.softening_strain`` gamma_s > 0, instead of ``relax_strain``): the
rule reads e_s = e_d + (e - e_d) (1 - exp(-g_d / gamma_s(p))), e_d the point's densest void ratio so far (the
smallest e of the run up to the accepted state), g_d the deviatoric strain accumulated since e was last at e_d (the
sum of d gamma over the increments that ended above it), gamma_s(p) = gamma_s (p / p_ref)^k exp(s (e0 - e_ref))
(k = ``relax_exponent``, s = ``relax_void_slope``, p of the accepted state). Before the peak (e at e_d,
contracting) e_s = e: the rise is not lagged; after it the interlocking is held near its peak and released to e's
over about gamma_s of distortion, and then reads e itself (unlike the lag, whose e_r trails e by about
gamma_r d e / d gamma as long as the point dilates).

Opt-in spread (``Interlocking.cell_spread`` s in [0, 1)): cell k of a point steps with tan phi (1 + s u_k) instead of
tan phi, u_k the uniform quantiles (2 j + 1) / n - 1 (j = 0 .. n - 1, n cells per point) dealt to the cells in the
order of the fractional parts of k (sqrt(5) - 1) / 2, the same for every point; so cells of one orientation class
(equal under the test's symmetry) reach their friction limit at different strains. The point's mean tan phi is
the rule's. A renewal's fresh cells step with the point's friction in the increment that renews them.

Opt-in state map (``Interlocking.map_state_weight`` w != 0; read by ``forward.density_alpha0``, not by the friction):
a test of void ratio e0 at confining pressure p0 builds its cell at the void-ratio map's alpha0 of
e_map = e0 + w lambda ((p0 / p_ref)^xi - 1) (``state_map_void_ratio``) instead of e0's. With w = 1 the cell stands for
the state parameter psi = e0 - e_c(p0) (Been & Jefferies 1985) carried to p_ref: e_map = e_c(p_ref) + psi. The
friction keeps reading e0.

Opt-in stiffness by density (``Interlocking.stiffness_void_slope`` s_k != 0; read by ``forward.simulate``, not by the
friction): a test's linear contact law runs kn exp(-s_k (e0 - e_ref)) (``stiffness_factor``; e_ref =
``RELAX_VOID_REF``, e0 the point's void ratio where J = 1, after kn's pressure factor), its critical-state renewal's
fresh cells too; s_k > 0 makes a looser specimen's contacts softer, so its elastic contraction lasts longer before
the cells slide and dilate. The form of Hardin & Richart's void-ratio function F(e) = (2.17 - e)^2 / (1 + e) of the
small-strain modulus as an exponential with a free slope (F's own: d ln F / d e = -1.9 at e = 0.55).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

from homogenization.material.density import current_void_ratio
from homogenization.material.homogenised import MaterialState, MaterialUpdate
from warp_hcell.core.dimension import dimension

P_REF = 101325.0
"""Reference pressure p_ref [Pa] of the critical-state line (one atmosphere)."""
E_C_FLOOR = 0.05
"""Smallest critical void ratio [-]: e_c(p) is clipped to it (counted: ``InterlockingFriction.floored``)."""
RELAX_VOID_REF = 0.55
"""Reference void ratio e_ref [-] of the lag's and the mobilisation's void-ratio factors exp(s (e0 - e_ref))."""
RELAX_VOID_SLOPE_MAX = 100.0
"""Largest abs(relax_void_slope) and abs(mobilisation_void_slope) [-] that ``Interlocking.check`` accepts."""
STIFFNESS_VOID_SLOPE_MAX = 100.0
"""Largest abs(stiffness_void_slope) [-] that ``Interlocking.check`` accepts."""
MAP_STATE_WEIGHT_MAX = 2.0
"""Largest abs(map_state_weight) [-] that ``Interlocking.check`` and ``forward.density_alpha0`` accept."""
MOBILISATION_EXPONENT = 2.0 / 3.0
"""Default exponent n of the mobilisation strain's pressure factor [-] (module docstring)."""
FIELDS = {"interlocking_m": "m", "e_gamma": "e_gamma", "lambda_c": "lambda_c", "xi_c": "xi",
          "cell_spread": "cell_spread", "mobilisation_strain": "mobilisation_strain",
          "mobilisation_start": "mobilisation_start", "relax_strain": "relax_strain",
          "relax_exponent": "relax_exponent", "softening_strain": "softening_strain",
          "relax_void_slope": "relax_void_slope", "mobilisation_exponent": "mobilisation_exponent",
          "mobilisation_void_slope": "mobilisation_void_slope", "map_state_weight": "map_state_weight",
          "stiffness_void_slope": "stiffness_void_slope"}
"""Per-set parameters (calibration name -> ``Interlocking`` field) that ``simulate`` reads from its params."""


@dataclass(frozen=True)
class Interlocking:
    """Parameters of the interlocking friction (module docstring), all [-] but p_ref.

    Attributes:
        m: interlocking exponent, >= 0 (0: phi_mu).
        e_gamma: critical void ratio at p = 0, > 0.
        lambda_c: the line's slope lambda, >= 0.
        xi: exponent of the line, in (0, 1].
        p_ref: reference pressure [Pa in 3D, N/m in 2D], > 0.
        relax_strain: gamma_r >= 0; 0: none.
        cell_spread: in [0, 1), the cells' half-spread; 0: none.
        mobilisation_strain: a_ref >= 0; 0: none.
        mobilisation_start: r0 in [0, 1], mobilised at zero distortion.
        relax_exponent: k, in [0, 3], the lag's pressure exponent.
        softening_strain: gamma_s, >= 0; 0: none; not with relax_strain.
        relax_void_slope: s, abs(s) <= 100, d ln(gamma_r) / d e0; 0: none.
        mobilisation_exponent: n, in [0, 3], its pressure exponent.
        mobilisation_void_slope: s_m, abs(s_m) <= 100, d ln(a) / d e0; 0: none.
        map_state_weight: w, in [-2, 2]; 0: none.
        stiffness_void_slope: s_k, abs <= 100; 0: none.
    """

    m: float = 1.0
    e_gamma: float = 0.7
    lambda_c: float = 0.05
    xi: float = 0.7
    p_ref: float = P_REF
    relax_strain: float = 0.0
    cell_spread: float = 0.0
    mobilisation_strain: float = 0.0
    mobilisation_start: float = 0.5
    relax_exponent: float = 0.0
    softening_strain: float = 0.0
    relax_void_slope: float = 0.0
    mobilisation_exponent: float = MOBILISATION_EXPONENT
    mobilisation_void_slope: float = 0.0
    map_state_weight: float = 0.0
    stiffness_void_slope: float = 0.0

    def check(self) -> None:
        """ValueError (one line) for a parameter out of range."""
        for name, ok in (("m", self.m >= 0.0), ("e_gamma", self.e_gamma > 0.0), ("lambda_c", self.lambda_c >= 0.0),
                         ("xi", 0.0 < self.xi <= 1.0), ("p_ref", self.p_ref > 0.0),
                         ("relax_strain", self.relax_strain >= 0.0), ("cell_spread", 0.0 <= self.cell_spread < 1.0),
                         ("mobilisation_strain", self.mobilisation_strain >= 0.0),
                         ("mobilisation_start", 0.0 <= self.mobilisation_start <= 1.0),
                         ("relax_exponent", 0.0 <= self.relax_exponent <= 3.0),
                         ("softening_strain", self.softening_strain >= 0.0),
                         ("relax_void_slope", abs(self.relax_void_slope) <= RELAX_VOID_SLOPE_MAX),
                         ("mobilisation_exponent", 0.0 <= self.mobilisation_exponent <= 3.0),
                         ("mobilisation_void_slope", abs(self.mobilisation_void_slope) <= RELAX_VOID_SLOPE_MAX),
                         ("map_state_weight", abs(self.map_state_weight) <= MAP_STATE_WEIGHT_MAX),
                         ("stiffness_void_slope", abs(self.stiffness_void_slope) <= STIFFNESS_VOID_SLOPE_MAX)):
            value = getattr(self, name)
            if not (math.isfinite(value) and ok):
                raise ValueError(f"interlocking {name} = {value:g} is out of range (Interlocking)")
        if self.softening_strain > 0.0 and self.relax_strain > 0.0:
            raise ValueError(f"interlocking softening_strain = {self.softening_strain:g} with relax_strain = "
                             f"{self.relax_strain:g}: one lag at a time (Interlocking)")


def critical_void_ratio(p: Any, e_gamma: Any, lambda_c: Any, xi: Any, p_ref: float) -> np.ndarray:
    """e_c(p) = e_Gamma - lambda (max(p, 0) / p_ref)^xi [-] (broadcast, xi too), before ``E_C_FLOOR``."""
    p = np.maximum(np.asarray(p, dtype=np.float64), 0.0)
    return np.asarray(e_gamma, dtype=np.float64) - np.asarray(lambda_c, dtype=np.float64) * (p / p_ref) ** xi


def state_map_void_ratio(e0: Any, p0: Any, w: Any, lambda_c: Any, xi: Any, p_ref: float) -> np.ndarray:
    """e_map = e0 + w lambda ((p0 / p_ref)^xi - 1) [-] (module docstring; broadcast; e0 [-], p0 > 0 [Pa], w, lambda,
    xi [-]): the void ratio whose map's alpha0 a test's cell is built at; exactly e0 where w = 0."""
    e0, w = np.asarray(e0, dtype=np.float64), np.asarray(w, dtype=np.float64)
    shift = w * np.asarray(lambda_c, dtype=np.float64) * ((np.asarray(p0, dtype=np.float64) / p_ref)
                                                           ** np.asarray(xi, dtype=np.float64) - 1.0)
    return np.where(w != 0.0, e0 + shift, e0)


def mobilised_friction_deg(phi_mu_deg: Any, e: Any, p: Any, m: Any, e_gamma: Any, lambda_c: Any, xi: Any,
                           p_ref: float) -> np.ndarray:
    """phi [deg] with tan phi = (e_c(p) / e)^m tan phi_mu (broadcast; e_c clipped to ``E_C_FLOOR``), in (0, 90)."""
    e_c = np.maximum(critical_void_ratio(p, e_gamma, lambda_c, xi, p_ref), E_C_FLOOR)
    ratio = e_c / np.asarray(e, dtype=np.float64)
    return np.degrees(np.arctan(ratio ** np.asarray(m, dtype=np.float64) * np.tan(np.radians(phi_mu_deg))))


def void_factor(e0: Any, s: Any) -> np.ndarray:
    """exp(s (e0 - ``RELAX_VOID_REF``)) [-] of initial void ratios ``e0`` [-] and slopes ``s`` [-] (broadcast); exactly
    1 where s = 0 (whatever e0, NaN included)."""
    s = np.asarray(s, dtype=np.float64)
    with np.errstate(all="ignore"):
        return np.where(s != 0.0, np.exp(s * (np.asarray(e0, dtype=np.float64) - RELAX_VOID_REF)), 1.0)


def stiffness_factor(e0: Any, s: Any) -> np.ndarray:
    """exp(-s (e0 - ``RELAX_VOID_REF``)) [-]: the factor on kn of a point of initial void ratio ``e0`` [-] with the
    slope ``s`` [-] (module docstring; broadcast); exactly 1 where s = 0 (whatever e0, NaN included)."""
    return void_factor(e0, -np.asarray(s, dtype=np.float64))


def mobilised_share(g: Any, p: Any, a_ref: Any, r0: Any, p_ref: float, e0: Any = RELAX_VOID_REF, s: Any = 0.0,
                    n: Any = MOBILISATION_EXPONENT) -> np.ndarray:
    """r = r0 + (1 - r0) g / (a + g) [-], a = a_ref (max(p, 0) / p_ref)^n exp(s (e0 - ``RELAX_VOID_REF``)) (module
    docstring; broadcast; p [Pa]), 1 where a_ref = 0; g [-] >= 0; s = 0: no void-ratio factor."""
    a = np.asarray(a_ref, dtype=np.float64) * (np.maximum(np.asarray(p, dtype=np.float64), 0.0) / p_ref) ** (
        np.asarray(n, dtype=np.float64)) * void_factor(e0, s)
    g = np.asarray(g, dtype=np.float64)
    r0 = np.asarray(r0, dtype=np.float64)
    with np.errstate(all="ignore"):
        r = r0 + (1.0 - r0) * g / (a + g)
    return np.where(np.asarray(a_ref) > 0.0, np.where(np.isfinite(r), r, 1.0), 1.0)


def relax_strain_at(p: Any, gamma_r: Any, k: Any, p_ref: float, e0: Any = RELAX_VOID_REF, s: Any = 0.0) -> np.ndarray:
    """The lag's strain gamma_r (max(p, 0) / p_ref)^k exp(s (e0 - ``RELAX_VOID_REF``)) [-] at mean stress ``p`` [Pa]
    of a point of initial void ratio ``e0`` [-] (module docstring; broadcast); s = 0: no void-ratio factor."""
    p = np.maximum(np.asarray(p, dtype=np.float64), 0.0)
    return np.asarray(gamma_r, dtype=np.float64) * (p / p_ref) ** np.asarray(k, dtype=np.float64) * void_factor(e0, s)


def spread_factors(n_cells: int, spread: float) -> np.ndarray:
    """Each cell's factor 1 + s u_k on tan phi (module docstring), shape (n_cells,), mean 1; ones where s = 0."""
    order = np.argsort(np.mod(np.arange(n_cells) * (math.sqrt(5.0) - 1.0) / 2.0, 1.0), kind="stable")
    u = np.empty(n_cells)
    u[order] = (2.0 * np.arange(n_cells) + 1.0) / n_cells - 1.0
    return 1.0 + spread * u


def friction_owner(model: Any) -> Any:
    """``model``, whose per-cell friction coefficient ``mu`` (n_cells,) its cells step with; ValueError (one line)
    where it holds none."""
    if np.ndim(getattr(model, "mu", None)) != 1:
        raise ValueError("the interlocking friction needs a cell model with per-cell laws (with_cell_laws)")
    return model


class InterlockingFriction:
    """The rule of the module docstring on a population, as ``MaterialPoints.renewal`` (wrapping ``inner``, a
    critical-state renewal or None, which runs first).

    Args:
        params: the rule (its fields that ``per_point`` lacks).
        material: the population (``forward.population(...).material``), n points of n_cells cells.
        state: its initial state (the friction is set from it).
        phi_mu_deg, e0: each point's phi_mu [deg] and void ratio at J = 1 [-], shapes (n,).
        per_point: per-point values, ``Interlocking`` field (not p_ref) -> shape (n,); None: ``params``'.
        inner: the renewal to run first (``calibration.renewal.PopulationRenewal``) or None.
        families: runs of cells per point (``opening_spread``'s families), each spread as a one-family point.
    Attributes (n,): ``friction_deg``, the friction now; ``floored``, increments whose e_c was clipped;
    ``fallbacks``, those whose friction fell back to phi_mu (``clip_log``: both per increment); ``e_lagged``, the
    void ratio read (e_r, e_s or e); ``e_densest``, e_d; ``since_densest``, g_d [-]; ``distortion``, g [-].
    """

    def __init__(self, params: Interlocking, material: Any, state: MaterialState, phi_mu_deg: np.ndarray,
                 e0: np.ndarray, per_point: Mapping[str, np.ndarray] | None = None, inner: Any = None,
                 families: int = 1) -> None:
        params.check()
        n = material.n_points
        self.params, self.material, self.inner = params, material, inner
        self.owner = friction_owner(material.model)
        self.n_cells = material.orient.n_cells
        if np.size(self.owner.mu) != n * self.n_cells:
            raise ValueError(f"the cell model holds {np.size(self.owner.mu)} frictions for {n} points of "
                             f"{self.n_cells} cells")
        keys = ("m", "e_gamma", "lambda_c", "xi", "cell_spread", "mobilisation_strain", "mobilisation_start",
                "relax_strain", "relax_exponent", "softening_strain", "relax_void_slope", "mobilisation_exponent",
                "mobilisation_void_slope")
        values = {name: getattr(params, name) for name in keys}
        values.update(per_point or {})
        (self.m, self.e_gamma, self.lambda_c, self.xi, self.cell_spread, self.mobilisation_strain,
         self.mobilisation_start, self.relax_strain, self.relax_exponent, self.softening_strain,
         self.relax_void_slope, self.mobilisation_exponent, self.mobilisation_void_slope) = (
            np.broadcast_to(np.asarray(values[k], dtype=np.float64), (n,)).copy() for k in keys)
        for i in range(n):
            replace(params, **{k: float(getattr(self, k)[i]) for k in keys}).check()
        self.mobilised = bool(np.any(self.mobilisation_strain > 0.0))
        self.lag_strain = np.where(self.relax_strain > 0.0, self.relax_strain, self.softening_strain)
        self.lagged = bool(np.any(self.lag_strain > 0.0))
        self.distortion = np.zeros(n)
        self.phi_mu_deg = np.broadcast_to(np.asarray(phi_mu_deg, dtype=np.float64), (n,)).copy()
        self.e0 = np.broadcast_to(np.asarray(e0, dtype=np.float64), (n,)).copy()
        self.floored = np.zeros(n, dtype=np.int64)
        self.fallbacks = np.zeros(n, dtype=np.int64)
        self.clip_log: list[tuple[np.ndarray, np.ndarray]] = []
        self.friction_deg = self.phi_mu_deg.copy()
        self._record = dimension(material.dim)
        self._mean = self._record.mean_stress
        self.e_lagged = current_void_ratio(self.e0, state.J)
        self.e_densest = self.e_lagged.copy()
        self.since_densest = np.zeros(n)
        if families < 1 or self.n_cells % families:
            raise ValueError(f"a point of {self.n_cells} cells holds no {families} families")
        u = np.tile(spread_factors(self.n_cells // families, 1.0) - 1.0, families)
        self.factors = (1.0 + self.cell_spread[:, None] * u[None, :]).ravel()
        self._strain = np.array(state.strain, dtype=np.float64)
        self.set_from(state)

    @property
    def count(self) -> Any:
        """The inner renewal's renewals per point (zeros without one)."""
        return self.inner.count if self.inner is not None else np.zeros(self.material.n_points, dtype=np.int64)

    @property
    def log(self) -> Any:
        """The inner renewal's log of events (``Renewal.log``), or None without one."""
        return self.inner.log if self.inner is not None else None

    def friction_at(self, state: MaterialState) -> np.ndarray:
        """The friction [deg] of each point at ``state`` (its J and p; with ``relax_strain`` or ``softening_strain``
        the lagged void ratio ``e_lagged`` instead of J's), shape (n,); phi_mu where not finite."""
        e = current_void_ratio(self.e0, state.J)
        if self.lagged:
            e = np.where(self.lag_strain > 0.0, self.e_lagged, e)
        p = self._mean(state.stress)
        with np.errstate(all="ignore"):
            e_c = critical_void_ratio(p, self.e_gamma, self.lambda_c, self.xi, self.params.p_ref)
            phi = mobilised_friction_deg(self.phi_mu_deg, e, p, self.m, self.e_gamma, self.lambda_c, self.xi,
                                         self.params.p_ref)
        self.floored += (e_c < E_C_FLOOR).astype(np.int64)
        usable = np.isfinite(phi) & (phi < 90.0)
        self.fallbacks += (~usable).astype(np.int64)
        return np.where(usable, phi, self.phi_mu_deg)

    def set_from(self, state: MaterialState) -> None:
        """Set every cell's friction (and the inner renewal's fresh cells') from ``state``."""
        self.friction_deg = self.friction_at(state)
        if self.mobilised:
            r = mobilised_share(self.distortion, self._mean(state.stress), self.mobilisation_strain,
                                self.mobilisation_start, self.params.p_ref, self.e0, self.mobilisation_void_slope,
                                self.mobilisation_exponent)
            self.friction_deg = np.degrees(np.arctan(r * np.tan(np.radians(self.friction_deg))))
        self.owner.mu = np.repeat(np.tan(np.radians(self.friction_deg)), self.n_cells) * self.factors
        if self.inner is not None:
            self.inner.set_friction(self.friction_deg)

    def within(self, start: MaterialState, update: MaterialUpdate) -> MaterialUpdate:
        """The inner renewal's ``within`` (the friction is fixed over an increment's trials)."""
        return self.inner.within(start, update) if self.inner is not None else update

    def advance(self, state: MaterialState) -> MaterialState:
        """The inner renewal's ``advance``, then the friction set from the accepted state for the next increment."""
        if self.inner is not None:
            state = self.inner.advance(state)
        if self.lagged or self.mobilised:
            gamma = self._distortion(state)
            if self.lagged:
                self.e_lagged = self._relaxed(state, gamma)
            if self.mobilised:
                self.distortion = self.distortion + np.where(np.isfinite(gamma), gamma, 0.0)
        self.set_from(state)
        self.clip_log.append((self.floored.copy(), self.fallbacks.copy()))
        return state

    def _distortion(self, state: MaterialState) -> np.ndarray:
        """The deviatoric strain d gamma [-] of the increment that ended at ``state`` (module docstring), shape (n,)."""
        d = np.array(state.strain, dtype=np.float64) - self._strain
        self._strain = np.array(state.strain, dtype=np.float64)
        d[:, self._record.dim:] /= self._record.shear_strain_factor  # engineering -> tensor shear
        return self._record.deviator(d)

    def _relaxed(self, state: MaterialState, gamma: np.ndarray) -> np.ndarray:
        """The void ratio the rule reads after the increment of deviatoric strain ``gamma`` ending at ``state``
        (e_r of the lag, e_s of the softening; module docstring), shape (n,); updates ``e_densest`` and
        ``since_densest``."""
        e = current_void_ratio(self.e0, state.J)
        gamma_r = relax_strain_at(self._mean(state.stress), self.lag_strain, self.relax_exponent, self.params.p_ref,
                                  self.e0, self.relax_void_slope)
        densest = e <= self.e_densest
        self.e_densest = np.where(densest, e, self.e_densest)
        self.since_densest = np.where(densest, 0.0, self.since_densest + np.where(np.isfinite(gamma), gamma, 0.0))
        with np.errstate(all="ignore"):
            lagged = e + (self.e_lagged - e) * np.exp(-gamma / gamma_r)
            held = self.e_densest + (e - self.e_densest) * -np.expm1(-self.since_densest / gamma_r)
        lagged = np.where(self.softening_strain > 0.0, held, lagged)
        return np.where(np.isfinite(lagged) & (self.lag_strain > 0.0), lagged, e)
