"""Forward model of a calibration: the biaxial or triaxial curves of a whole population of parameter sets.

``simulate(test, params, settings)`` runs the test (isotropic compression to p0, then
constant-volume or drained shear) for n parameter sets at once and returns the model's q, p
and eps_v at the measured eps1 values. With the analytical backend the n sets are ONE
``HomogenisedMaterial`` (of the test's dimension) of n material
points, each with its own cells (``AnalyticalCell.with_cell_laws`` /
``Analytical3DCell.with_cell_laws``: per-cell kn, kt/kn, phi_g and alpha0; with the Hertz-Mindlin
law ``Analytical3DCell.with_hertz_cell_laws``: per-cell G, nu, phi_g and alpha0; with ``alpha0_spread`` the
point's cells in ``opening_spread.N_NODES`` families of alpha0, ``homogenization.material.opening_spread``), so every increment
is one batched ``step`` over n x (cells per point) cells, run by the element-test engine
(``homogenization.element_test``: the population's stages as plans, its one stress-control solver
under the ``POPULATION`` policy). Other backends take one contact law per model: their sets run
one after the other through ``homogenization.element_test.driver.run``. Both orient the cells as the driver
does (``element_test.points.orientation_set``).

Stages, per point, as in ``homogenization.element_test.programme.biaxial`` / ``programme.triaxial``: equal strain
increments of ``iso_increment`` on every normal component until p reaches p0, the increment
that crosses it shortened (regula falsi on its scale) so that p lands on p0; then ``increment``
steps of eps11 with the lateral strains constant-volume (2D: d_eps22 = -d_eps11; 3D:
``programme.isochoric``, d_eps22 = d_eps33) or solved by Newton so that every lateral stress is p0
(drained). A point is advanced only while its stage lasts (the others keep their state), so a
point's curve does not depend on the population it runs in.

Units: stresses [N/m] (2D) or [Pa] (3D), strains [-], compression and contraction positive;
eps1 and eps_v are counted from the end of the isotropic stage. 3D: q = sqrt(3 J2), p = tr(sigma) / 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.backends import backend_class, make_cell_model
from homogenization.calibration.data import Measurement
from homogenization.calibration.interlocking import (FIELDS as INTERLOCKING, MAP_STATE_WEIGHT_MAX,
                                                     STIFFNESS_VOID_SLOPE_MAX, Interlocking, InterlockingFriction,
                                                     state_map_void_ratio, stiffness_factor)
from homogenization.calibration.renewal import PopulationRenewal, laws_of
from homogenization.element_test.points import MaterialPoints, material_points, orientation_set
from homogenization.element_test.plan import Plan
from homogenization.element_test.record import History
from homogenization.element_test.stages import run_stages
from homogenization.element_test.solver import POPULATION, StressControl
from homogenization.material import opening_spread
from homogenization.material import orientation as orient_mod
from homogenization.material.critical_state import CriticalState
from homogenization.material.density import (DEFAULT_E_MAX, DEFAULT_E_MIN, OPENING_RANGE_DEG, default_map,
                                              opening_angle_deg)
from warp_hcell.core.parameters import CellDefaults, ContactLaw, HertzMindlinLaw, Law, LoadingDefaults
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.hcell import plain_h_cell

DENSITY = ("e_min", "e_max")
"""The void-ratio map's parameters [-] (``homogenization.material.density``): a test that gives its void
ratio (``Measurement.void_ratio``) runs at the map's alpha0 instead of alpha0; read only for such tests."""
RULE = {"alpha_c": "alpha_c_deg", "renewal_rate": "rate"}
"""The critical-state rule's calibratable parameters (CLI name -> ``CriticalState`` field): alpha_c [deg], the
opening angle where the density feedback changes sign, and renewal_rate [-]; read only with
``ForwardSettings.critical_state``, per set (the rule's other fields: the settings' rule)."""
RULE_PRIOR = {"alpha_c": (46.0, 58.0, False), "renewal_rate": (1.0, 400.0, True)}
"""Default prior of the rule's parameters: uniform (low, high, log-uniform?); alpha_c within the clip of the fresh
angles of both dimensions' ``DEFAULTS``, renewal_rate below both rate_max."""
CONTACT_LAW_KEY = "contact_law"
"""Key of posterior.json holding a non-linear contact law at the posterior mean (``to_dict``); absent: the linear law."""
CRITICAL_STATE_KEY = "critical_state"
"""Key of posterior.json (and of run.json's forward settings) holding the critical-state rule at the posterior
mean (``dataclasses.asdict``); absent: the plain cell."""
MAP_STATE = "map_state_weight"
"""The interlocking's state-map weight w [-] (``interlocking.state_map_void_ratio``): read by ``density_alpha0`` (the
cell's alpha0), not by the friction."""
STIFFNESS = "stiffness_void_slope"
"""The interlocking's stiffness slope s_k [-] (``interlocking.stiffness_factor``): read by ``simulate`` (each set's kn
times exp(-s_k (e0 - 0.55)), linear law), not by the friction."""
INTERLOCKING_PRIOR = {"interlocking_m": (0.0, 6.0, False), "e_gamma": (0.5, 1.2, False), "lambda_c": (0.0, 0.4, False),
                      "xi_c": (0.2, 1.0, False), "cell_spread": (0.0, 0.6, False),
                      "mobilisation_strain": (0.0, 0.05, False), "mobilisation_start": (0.0, 1.0, False),
                      "relax_strain": (0.0, 0.1, False), "relax_exponent": (0.0, 2.0, False),
                      "softening_strain": (0.0, 0.1, False), "relax_void_slope": (0.0, 30.0, False),
                      "mobilisation_exponent": (0.0, 2.0, False), "mobilisation_void_slope": (0.0, 30.0, False),
                      MAP_STATE: (0.0, 2.0, False), STIFFNESS: (0.0, 30.0, False)}
"""Default prior of the interlocking friction's calibratable parameters (``INTERLOCKING``: CLI name -> ``Interlocking``
field): uniform (low, high, log-uniform?), all [-]; read only with ``ForwardSettings.interlocking``, per set."""
INTERLOCKING_KEY = "interlocking"
"""Key of posterior.json (and of run.json's forward settings) holding the interlocking friction at the posterior mean
(``dataclasses.asdict`` of ``Interlocking``); absent: none."""
KN_EXPONENT = "kn_exponent"
"""The calibratable exponent n [-] of the linear law's kn on a triaxial test, kn (p0 / kn_p_ref)^n, per set (opt-in:
calibrated in its place of ``ForwardSettings.kn_exponent``; ``kn_at_pressure``)."""
KN_EXPONENT_PRIOR = (0.0, 1.0, False)
"""Default prior of kn_exponent [-]: uniform (low, high, log-uniform?)."""
PARAMETERS = ("phi_g", "kn", "kt_over_kn", "alpha0", "shear_modulus", "poisson", opening_spread.NAME, *DENSITY, *RULE,
              *INTERLOCKING, KN_EXPONENT)
"""Names of the calibratable parameters, in the units of the CLI flags: phi_g [deg], kn [N/m],
kt_over_kn [-], alpha0 [deg], shear_modulus G [Pa], poisson nu [-], alpha0_spread [deg], e_min and
e_max [-], alpha_c [deg] and renewal_rate [-] (``RULE``), the interlocking friction's m, e_gamma, lambda_c,
xi_c, cell_spread, mobilisation_strain, mobilisation_start, relax_strain, relax_exponent, softening_strain,
relax_void_slope, mobilisation_exponent, mobilisation_void_slope, map_state_weight and stiffness_void_slope [-]
(``INTERLOCKING``), kn's
exponent [-] (``KN_EXPONENT``, linear law)."""
LAW_PARAMETERS = {ContactLaw.name: ("phi_g", "kn", "kt_over_kn", "alpha0"),
                  HertzMindlinLaw.name: ("phi_g", "shear_modulus", "poisson", "alpha0")}
"""The parameters of ``PARAMETERS`` that each contact law's forward model reads."""
SPREAD = opening_spread.NAME
"""The half-width [deg] of a point's uniform distribution of opening angles about alpha0
(``homogenization.material.opening_spread``; triaxial tests, analytical backend, either law): read
only where calibrated or set nonzero in ``ForwardSettings.fixed``, so that without it the forward
model is the single-alpha0 one, bit for bit."""
SPREAD_PRIOR = (0.0, 10.0, False)
"""Default prior of alpha0_spread [deg]: uniform (low, high, log-uniform?), further cut by
alpha0 - alpha0_spread >= ALPHA_MIN_3D_DEG."""


DENSITY_DEFAULTS = (DEFAULT_E_MIN, DEFAULT_E_MAX)
"""e_min and e_max [-] where neither calibrated nor in ``ForwardSettings.fixed``."""
DENSITY_PRIOR = {"e_min": (0.3, 0.8, False), "e_max": (0.8, 1.4, False)}
"""Default prior of e_min and e_max [-]: uniform (low, high, log-uniform?), apart so that e_min < e_max;
a set whose [e_min, e_max] does not hold a test's void ratio fails (log L = -inf)."""


def calibratable(law: str) -> tuple[str, ...]:
    """The parameters a calibration of ``law`` may vary: the law's, the spread of alpha0, the void-ratio map's,
    the critical-state rule's (``RULE``), the interlocking friction's (``INTERLOCKING``) and, for the linear law,
    kn's exponent (``KN_EXPONENT``) and its stiffness slope (``STIFFNESS``)."""
    own = (KN_EXPONENT,) if law == ContactLaw.name else ()
    interlocking = tuple(n for n in INTERLOCKING if n != STIFFNESS or law == ContactLaw.name)
    return LAW_PARAMETERS[law] + (SPREAD,) + DENSITY + tuple(RULE) + interlocking + own


def rule_at(values: Mapping[str, float], settings: "ForwardSettings") -> CriticalState | None:
    """The settings' critical-state rule with the fields of ``RULE`` that ``values`` (CLI names, floats) holds
    replaced; None without a rule."""
    if settings.critical_state is None:
        return None
    return replace(settings.critical_state, **{RULE[name]: float(v) for name, v in values.items() if name in RULE})


def interlocking_at(values: Mapping[str, float], settings: "ForwardSettings") -> Interlocking | None:
    """The settings' interlocking friction with the fields of ``INTERLOCKING`` that ``values`` (CLI names, floats)
    holds replaced; None without one."""
    if settings.interlocking is None:
        return None
    return replace(settings.interlocking, **{INTERLOCKING[n]: float(v) for n, v in values.items() if n in INTERLOCKING})


@dataclass(frozen=True)
class ForwardSettings:
    """Numerical settings of the forward model.

    Attributes:
        law: contact law, a name of ``LAW_PARAMETERS`` ("hertz-mindlin": 3D tests only).
        backend: "analytical" (batched), "dem" or "ann".
        n_orientations: cell orientations per material point of a 2D test [-].
        lebedev_order, n_spins: cell orientations of a triaxial test (``orientation.orientations_3d``).
        staggered_spins: stagger the spins from axis to axis; False keeps the rule's cube symmetry.
        increment: axial strain increment of the shear [-].
        iso_increment: strain increment per component, isotropic stage [-].
        radius: grain radius [m].
        stress_rtol: relative tolerance of p = p0 (landing) and sigma22 = p0 (drained) [-].
        max_newton: Newton iterations per drained increment [-].
        fixed: value of every parameter not calibrated (CLI flag units).
        backend_options: the backend's keyword options (dem/ann).
        critical_state: the cells' renewal rule (``material.critical_state``; None: none), on each set's
            void-ratio map.
        kinematics: 3D cells' kinematics (``orientation.KINEMATICS``).
        kn_exponent, kn_p_ref [Pa]: triaxial tests run kn (p0 / kn_p_ref)^kn_exponent, ``kn_at_pressure``.
        interlocking: ``calibration.interlocking``'s friction, or None."""

    law: str = ContactLaw.name
    backend: str = "analytical"
    n_orientations: int = 36
    lebedev_order: int = 11
    n_spins: int = 4
    staggered_spins: bool = False
    increment: float = 1e-3
    iso_increment: float = 5e-4
    radius: float = CellDefaults.radius
    stress_rtol: float = LoadingDefaults.stress_rtol
    max_newton: int = LoadingDefaults.max_newton_iterations
    fixed: Mapping[str, float] = field(default_factory=lambda: {
        "phi_g": ContactLaw.phi_g_deg, "kn": ContactLaw.kn, "kt_over_kn": ContactLaw.kt_over_kn,
        "alpha0": CellDefaults.alpha0_deg, "shear_modulus": HertzMindlinLaw.shear_modulus,
        "poisson": HertzMindlinLaw.poisson})
    backend_options: Mapping[str, object] = field(default_factory=dict)
    critical_state: CriticalState | None = None
    kinematics: str = "projected"
    kn_exponent: float = 0.0
    kn_p_ref: float = 101325.0
    interlocking: Interlocking | None = None

    @property
    def parameters(self) -> tuple[str, ...]:
        """The parameters the forward model of ``law`` reads (``LAW_PARAMETERS``)."""
        return LAW_PARAMETERS[self.law]


def settings_record(settings: ForwardSettings) -> dict:
    """``settings`` as a JSON-able dict (``fixed`` a plain dict); ``kn_exponent`` and ``kn_p_ref`` only where the
    exponent is nonzero, ``interlocking`` only where set, so that the record of a run without them reads as before
    those options existed."""
    from dataclasses import asdict  # noqa: PLC0415

    record = {**asdict(settings), "fixed": dict(settings.fixed)}
    if settings.kn_exponent == 0.0:
        del record["kn_exponent"], record["kn_p_ref"]
    if settings.interlocking is None:
        del record["interlocking"]
    return record


@dataclass
class Curves:
    """Model curves of n parameter sets at a test's eps1 values, each shape (n, n_data), and per-point counts, each
    shape (n,).

    ``q``, ``p`` [N/m in 2D, Pa in 3D], ``eps_v`` [-]; NaN for a point whose isotropic stage does not reach p0
    within ``homogenization.element_test.programme.ISO_MAX_STRAIN`` (too soft). ``n_fallback``: the isotropic
    landings and drained Newton iterations that did not meet ``stress_rtol`` (their last iterate is used), or
    (dem/ann, one set at a time) 1 where the backend reported unconverged cells; ``n_jump``: the drained increments
    whose lateral stress jumps across its target, solved at the jump (``element_test.solver``, the nearer side);
    ``n_clip``: the increments at which the interlocking friction floored its e_c (``E_C_FLOOR``) or fell back to
    phi_mu (``InterlockingFriction.floored`` + ``fallbacks``); ``n_renewal_clip``: the renewal's increments with a
    capped rate plus its cells renewed at a clipped angle (``Renewal.capped`` + ``clipped``); zeros without a rule.
    """

    q: np.ndarray
    p: np.ndarray
    eps_v: np.ndarray
    n_fallback: np.ndarray
    n_jump: np.ndarray
    n_clip: np.ndarray
    n_renewal_clip: np.ndarray

    def channel(self, name: str) -> np.ndarray:
        """The curve of ``name`` ("q", "p" or "eps_v")."""
        return getattr(self, name)


def full_parameters(params: Mapping[str, np.ndarray], settings: ForwardSettings) -> dict[str, np.ndarray]:
    """The four parameters of the settings' law (``settings.parameters``) as arrays of one shape (n,):
    the calibrated ones, the others fixed; and ``SPREAD`` where calibrated or fixed nonzero."""
    n = len(np.atleast_1d(next(iter(params.values())))) if params else 1
    names = settings.parameters + ((SPREAD,) if uses_spread(params, settings) else ())
    return {name: np.broadcast_to(np.asarray(params[name] if name in params else settings.fixed[name],
                                             dtype=np.float64), (n,)).copy()
            for name in names}


def uses_spread(params: Mapping[str, object], settings: ForwardSettings) -> bool:
    """Whether the forward model runs a distribution of opening angles: ``SPREAD`` calibrated or fixed nonzero."""
    return SPREAD in params or float(settings.fixed.get(SPREAD, 0.0)) != 0.0


def feasible(values: Mapping[str, np.ndarray], settings: ForwardSettings) -> np.ndarray | None:
    """Per set, whether its alpha0 and spread are allowed (``opening_spread.feasible``), shape (n,); None
    where the forward model runs no spread (every set allowed)."""
    if not uses_spread(values, settings):
        return None
    full = full_parameters(values, settings)
    return opening_spread.feasible(full["alpha0"], full[SPREAD])


def simulate(test: Measurement, params: Mapping[str, np.ndarray], settings: ForwardSettings, *,
             interlocking: Interlocking | None = None) -> Curves:
    """Curves of ``test`` for each parameter set; ``params`` maps names of ``settings.parameters`` (and of
    ``DENSITY``) to shape (n,). A test that gives its void ratio runs each set at its map's alpha0
    (``density_alpha0``); NaN curves for a set whose [e_min, e_max] misses it or whose
    alpha0 - alpha0_spread is then below 45 deg.
    ``interlocking`` (analytical backend): phi_g is each set's phi_mu of the interlocking friction,
    e0 the test's void ratio, else the set's map's of its alpha0; its fields per set where ``params`` holds
    ``INTERLOCKING``'s names; None: ``settings.interlocking`` (None: the plain law). ``KN_EXPONENT`` in ``params``: each
    set's exponent of kn (``kn_at_pressure``). ``STIFFNESS``: kn times ``interlocking.stiffness_factor`` of e0.

    Raises:
        ValueError: a value out of range, the Hertz-Mindlin law on a 2D test (or with ``STIFFNESS``),
            alpha0_spread on a 2D test or off the analytical backend (one line).
        homogenization.element_test.driver.ControlError: (dem/ann) a stage that cannot be run (p0 not reached).
    """
    if settings.law == HertzMindlinLaw.name and test.dim != 3:
        raise ValueError(f"the Hertz-Mindlin contact law is defined for spheres: {test.name} is a biaxial (2D) "
                         f"test; calibrate it on triaxial data")
    full = full_parameters(params, settings)
    if KN_EXPONENT in params:  # per set, in place of the settings' exponent
        full[KN_EXPONENT] = np.broadcast_to(np.asarray(params[KN_EXPONENT], dtype=np.float64), full["phi_g"].shape).copy()
    interlocking = settings.interlocking if interlocking is None else interlocking
    if interlocking is None and any(name in params for name in INTERLOCKING):
        raise ValueError(f"{', '.join(n for n in INTERLOCKING if n in params)}: parameters of the interlocking "
                         f"friction; the forward model runs none (ForwardSettings.interlocking)")
    if settings.critical_state is None and any(name in params for name in RULE):
        raise ValueError(f"{', '.join(n for n in RULE if n in params)}: parameters of the critical-state rule; the "
                         f"forward model runs none (ForwardSettings.critical_state)")
    for name in RULE:  # the rule's calibrated parameters, per set
        if name in params:
            full[name] = np.broadcast_to(np.asarray(params[name], dtype=np.float64), full["phi_g"].shape).copy()
    if settings.critical_state is not None:  # the renewal's map, per set
        for name, default in zip(DENSITY, DENSITY_DEFAULTS):
            value = params[name] if name in params else settings.fixed.get(name, default)
            full[name] = np.broadcast_to(np.asarray(value, dtype=np.float64), full["phi_g"].shape).copy()
    if interlocking is not None:
        full.update(_interlocking_values(test, params, full, settings))
    alpha0 = density_alpha0(test, params, settings, interlocking)
    if alpha0 is not None:
        reached = np.isfinite(alpha0)
        if SPREAD in full:  # the lowest family of the map's alpha0 must be a ten-sphere cell
            reached = reached & opening_spread.feasible(np.where(reached, alpha0, 90.0), full[SPREAD])
        full["alpha0"] = np.where(reached, alpha0, full["alpha0"])
        if not reached.all():
            return _unreached(test, full, settings, reached, interlocking)
    if SPREAD in full:
        if test.dim != 3 or settings.backend != "analytical":
            raise ValueError(f"alpha0_spread runs on triaxial tests with the analytical backend only ({test.name}: "
                             f"{'biaxial' if test.dim != 3 else 'backend ' + settings.backend})")
        opening_spread.check(full["alpha0"], full[SPREAD])
    if interlocking is not None and settings.backend != "analytical":
        raise ValueError("the interlocking friction runs with the analytical backend only")
    if KN_EXPONENT in full:
        full["kn"] = kn_at_pressure(full.get("kn"), test, settings, exponent=full[KN_EXPONENT])
    elif settings.kn_exponent != 0.0:
        full["kn"] = kn_at_pressure(full.get("kn"), test, settings)
    if interlocking is not None and (STIFFNESS in full or interlocking.stiffness_void_slope != 0.0):
        if settings.law != ContactLaw.name:
            raise ValueError(f"{STIFFNESS} scales the linear law's kn; the {settings.law} law has none")
        slope = np.broadcast_to(np.asarray(full.get(STIFFNESS, interlocking.stiffness_void_slope)), full["kn"].shape)
        if not np.all(np.abs(slope) <= STIFFNESS_VOID_SLOPE_MAX):
            bad = slope[~(np.abs(slope) <= STIFFNESS_VOID_SLOPE_MAX)][0]
            raise ValueError(f"{STIFFNESS} = {bad:g} is out of range [-{STIFFNESS_VOID_SLOPE_MAX:g}, "
                             f"{STIFFNESS_VOID_SLOPE_MAX:g}]")
        full["kn"] = full["kn"] * stiffness_factor(full[E0], slope)
    if settings.backend == "analytical":
        points = population(full, settings, test.dim)
        if settings.critical_state is not None:
            points.renewal = _renewal(full, settings, points)
        if interlocking is not None:
            points.renewal = InterlockingFriction(interlocking, points.material, points.state, full["phi_g"], full[E0],
                                                  {f: full[name] for name, f in INTERLOCKING.items()
                                                   if name in full and name not in (MAP_STATE, STIFFNESS)} or None,
                                                  inner=points.renewal,
                                                  families=opening_spread.N_NODES if SPREAD in full else 1)
        return simulate_points(test, points, settings)
    return _simulate_one_by_one(test, full, settings)


def kn_factor(p0: float, settings: ForwardSettings) -> float:
    """(p0 / kn_p_ref)^kn_exponent [-]: the factor on the linear law's kn at confining pressure ``p0`` [Pa]; 1 without
    the exponent."""
    return (p0 / settings.kn_p_ref) ** settings.kn_exponent if settings.kn_exponent else 1.0


def kn_at_pressure(kn: np.ndarray, test: Measurement, settings: ForwardSettings,
                   exponent: np.ndarray | None = None) -> np.ndarray:
    """The linear law's normal stiffness [N/m] that ``test`` runs: kn (p0 / kn_p_ref)^kn_exponent, shape of ``kn``
    (its value at kn_p_ref; ``ForwardSettings``), a secant stiffness set once per test from its confining pressure;
    ``exponent`` (shape of ``kn``, [-]): each set's own (a calibrated ``KN_EXPONENT``) instead of the settings'.

    Raises:
        ValueError: a nonzero or calibrated exponent with another law than the linear one or on a biaxial test
            (its p0 is in N/m, not a pressure) (one line)."""
    if exponent is None and settings.kn_exponent == 0.0:
        return kn
    if settings.law != ContactLaw.name or test.dim != 3:
        raise ValueError(f"kn_exponent scales the linear law's kn on triaxial tests only ({test.name}: "
                         f"{'law ' + settings.law if settings.law != ContactLaw.name else 'biaxial'})")
    if exponent is not None:
        return kn * (test.p0 / settings.kn_p_ref) ** np.asarray(exponent, dtype=np.float64)
    return kn * kn_factor(test.p0, settings)


E0 = "interlocking_e0"
"""Key of ``simulate``'s per-set values: each set's void ratio at J = 1 [-] for the interlocking friction."""


def _interlocking_values(test: Measurement, params: Mapping[str, np.ndarray], full: dict[str, np.ndarray],
                         settings: ForwardSettings) -> dict[str, np.ndarray]:
    """Per set: e0 [-] (``E0``: given in ``params``, else the test's void ratio, else the set's map's of its alpha0) and the interlocking
    parameters that ``params`` holds (``INTERLOCKING``), shapes (n,)."""
    n = full["phi_g"].size
    if E0 in params:  # a subset of sets (``_unreached``)
        e0 = np.broadcast_to(np.asarray(params[E0], dtype=np.float64), (n,)).copy()
    elif test.void_ratio is not None:
        e0 = np.full(n, float(test.void_ratio))
    else:
        e_min, e_max = (np.broadcast_to(np.asarray(params[name] if name in params else settings.fixed.get(name, default),
                                                   dtype=np.float64), (n,)) for name, default in zip(DENSITY, DENSITY_DEFAULTS))
        dense, loose = OPENING_RANGE_DEG[test.dim]
        e0 = e_max - (loose - full["alpha0"]) / (loose - dense) * (e_max - e_min)
    out = {name: np.broadcast_to(np.asarray(params[name], dtype=np.float64), (n,)).copy()
           for name in INTERLOCKING if name in params}
    return {**out, E0: e0}


def _renewal(full: dict[str, np.ndarray], settings: ForwardSettings, points: MaterialPoints) -> PopulationRenewal:
    """The critical-state renewal of a population (``calibration.renewal``) on each set's void-ratio map (``full``'s
    e_min and e_max: calibrated, else fixed, else the defaults); with ``SPREAD``, each family of a point renewed on
    its own void ratio."""
    bounds = (full["e_min"], full["e_max"])
    per_point = {field: full[name] for name, field in RULE.items() if name in full}
    return PopulationRenewal(settings.critical_state, points.material, points.state, default_map(points.dim),
                             full["alpha0"], laws_of(full, settings.law), settings.law, settings.radius,
                             per_point=per_point or None, e_bounds=bounds, spread_deg=full.get(SPREAD))


def density_alpha0(test: Measurement, params: Mapping[str, np.ndarray], settings: ForwardSettings,
                   interlocking: Interlocking | None = None) -> np.ndarray | None:
    """Per set, the alpha0 [deg] of a test that gives its void ratio: the map of ``density.default_map(test.dim)``
    between the set's e_min and e_max (calibrated, else ``settings.fixed``, else the defaults) at that void ratio,
    or, with a state-map weight w (``MAP_STATE``: per set in ``params``, else the interlocking's), at
    ``interlocking.state_map_void_ratio`` of it at the test's p0 on the set's line (lambda_c and xi_c: per set in
    ``params``, else the interlocking's; w = 0: the void ratio itself); NaN where [e_min, e_max] does not hold that
    void ratio; None for a test without one. ``interlocking``: None: ``settings.interlocking`` (None: no state map).
    ValueError (one line) for a w outside [-2, 2] (``interlocking.MAP_STATE_WEIGHT_MAX``)."""
    if test.void_ratio is None:
        return None
    n = len(np.atleast_1d(next(iter(params.values())))) if params else 1
    bounds = [np.broadcast_to(np.asarray(params[name] if name in params else settings.fixed.get(name, default),
                                         dtype=np.float64), (n,)) for name, default in zip(DENSITY, DENSITY_DEFAULTS)]
    interlocking = settings.interlocking if interlocking is None else interlocking
    e = test.void_ratio
    if interlocking is not None and (MAP_STATE in params or interlocking.map_state_weight != 0.0):
        line = {name: np.broadcast_to(np.asarray(params[name] if name in params else getattr(interlocking, field),
                                                 dtype=np.float64), (n,))
                for name, field in ((MAP_STATE, MAP_STATE), ("lambda_c", "lambda_c"), ("xi_c", "xi"))}
        outside = line[MAP_STATE][~(np.abs(line[MAP_STATE]) <= MAP_STATE_WEIGHT_MAX)]
        if outside.size:
            raise ValueError(f"{MAP_STATE} = {outside[0]:g} is out of range [-{MAP_STATE_WEIGHT_MAX:g}, "
                             f"{MAP_STATE_WEIGHT_MAX:g}]")
        e = state_map_void_ratio(e, test.p0, line[MAP_STATE], line["lambda_c"], line["xi_c"], interlocking.p_ref)
    return opening_angle_deg(e, *bounds, *OPENING_RANGE_DEG[test.dim])


def with_density(settings: ForwardSettings, tests: Sequence[Measurement], e_min: float, e_max: float) -> ForwardSettings:
    """``settings`` with ``e_min`` and ``e_max`` [-] fixed where a test gives its void ratio (else unchanged, so
    that the settings of a calibration without void ratios read as before)."""
    if all(t.void_ratio is None for t in tests):
        return settings
    return replace(settings, fixed={**settings.fixed, "e_min": float(e_min), "e_max": float(e_max)})


def check_density(tests: Sequence[Measurement], calibrated: Sequence[str], settings: ForwardSettings,
                  bounds: Mapping[str, tuple[float, float]]) -> None:
    """Before any run: ValueError (one line) for e_min or e_max calibrated where no test gives its void ratio,
    alpha0 calibrated where every test gives one (the map sets it), fixed e_min >= e_max, or a test whose void
    ratio no map reaches: outside [e_min, e_max], each end the prior's far bound (``bounds``: name ->
    (low, high)) where calibrated, else its fixed value."""
    given = [t for t in tests if t.void_ratio is not None]
    fitted = [name for name in calibrated if name in DENSITY]
    if fitted and not given:
        raise ValueError(f"--params {fitted[0]}: no --data file gives its void ratio ('# void_ratio = E' in its "
                         f"header), so the void-ratio map is not used")
    if "alpha0" in calibrated and given and len(given) == len(tests):
        raise ValueError("--params alpha0: every --data file gives its void ratio, which sets alpha0 through the "
                         "void-ratio map; calibrate e_min,e_max instead")
    fixed = [float(settings.fixed.get(name, default)) for name, default in zip(DENSITY, DENSITY_DEFAULTS)]
    if not fitted and given and not fixed[0] < fixed[1]:
        raise ValueError(f"--e-min {fixed[0]:g} must be below --e-max {fixed[1]:g}")
    low = bounds["e_min"][0] if "e_min" in calibrated else fixed[0]
    high = bounds["e_max"][1] if "e_max" in calibrated else fixed[1]
    for test in given:
        if not low <= test.void_ratio <= high:
            raise ValueError(f"{test.path}: void_ratio = {test.void_ratio:g} is outside what the void-ratio map "
                             f"reaches, [{low:g}, {high:g}] (e_min to e_max, over the prior where calibrated); give "
                             f"--e-min/--e-max or a prior that hold it")


def _unreached(test: Measurement, full: dict[str, np.ndarray], settings: ForwardSettings,
               reached: np.ndarray, interlocking: Interlocking | None = None) -> Curves:
    """``simulate`` of the sets whose map reaches the test's void ratio; NaN curves for the others."""
    n = reached.size
    out = Curves(*(np.full((n, test.eps1.size), np.nan) for _ in range(3)),
                 *(np.zeros(n, dtype=np.int64) for _ in range(4)))
    if reached.any():
        subset = {name: values[reached] for name, values in full.items()}  # alpha0 already mapped
        part = simulate(replace(test, void_ratio=None), subset, settings, interlocking=interlocking)
        for name in ("q", "p", "eps_v", "n_fallback", "n_jump", "n_clip", "n_renewal_clip"):
            getattr(out, name)[reached] = getattr(part, name)
    return out


SHEAR_TESTS: dict[int, Callable[..., programmes.Programme]] = {
    2: programmes.biaxial,
    3: lambda p0, eps_max, increment, *, iso_increment, drained: programmes.triaxial(
        p0, eps_max, increment, test="drained" if drained else "undrained", iso_increment=iso_increment),
}
"""Dimension of a test -> its programme ``(p0, eps_max, increment, *, iso_increment, drained)``: the
biaxial (2) or triaxial (3) test, drained or undrained (``element_test.programme``)."""


def _n_shear(test: Measurement, settings: ForwardSettings) -> int:
    return max(1, math.ceil(float(test.eps1.max()) / settings.increment - 1e-9))


def _sample(eps1_model: np.ndarray, values: np.ndarray, eps1: np.ndarray) -> np.ndarray:
    """Linear interpolation of values (n, m) given on eps1_model (m,) at eps1 (k,)."""
    j = np.clip(np.searchsorted(eps1_model, eps1, side="right") - 1, 0, eps1_model.size - 2)
    w = (eps1 - eps1_model[j]) / (eps1_model[j + 1] - eps1_model[j])
    return values[:, j] * (1.0 - w) + values[:, j + 1] * w


def population(full: dict[str, np.ndarray], settings: ForwardSettings, dim: int) -> MaterialPoints:
    """One material point per parameter set, each with its own cells (per-cell contact law: kn and kt/kn,
    or G and nu; phi_g and alpha0; with ``SPREAD``, ``opening_spread.N_NODES`` families of alpha0), oriented as the driver orients the H-cell (``element_test.points.orientation_set``)."""
    n = full["phi_g"].size
    cell_class, meso = backend_class("analytical", dim), plain_h_cell(dim, CellDefaults.alpha0_deg, settings.radius)
    orient = orientation_set(meso, n_orientations=settings.n_orientations, lebedev_order=settings.lebedev_order,
                             n_spins=settings.n_spins, staggered_spins=settings.staggered_spins)
    if dim == 3 and settings.kinematics != "projected":
        orient = orient_mod.orientations_3d(settings.lebedev_order, settings.n_spins,
                                            spin_period_deg=meso.spin_period_deg(),
                                            staggered=settings.staggered_spins, kinematics=settings.kinematics)
    if SPREAD in full:
        alpha0 = opening_spread.cell_alpha0(full["alpha0"], full[SPREAD], orient.n_cells)
        orient = opening_spread.replicate(orient)
        per_cell = {name: np.repeat(values, orient.n_cells) for name, values in full.items() if name != SPREAD}
        per_cell["alpha0"] = alpha0
    else:
        per_cell = {name: np.repeat(values, orient.n_cells) for name, values in full.items()}
    if settings.law == HertzMindlinLaw.name:
        model = cell_class.with_hertz_cell_laws(per_cell["shear_modulus"], per_cell["poisson"], per_cell["phi_g"],
                                                settings.radius, alpha0_deg=per_cell["alpha0"])
    else:
        model = cell_class.with_cell_laws(per_cell["kn"], per_cell["kt_over_kn"], per_cell["phi_g"], settings.radius,
                                          alpha0_deg=per_cell["alpha0"])
    return material_points(model, meso, n, orient)


def stages(test: Measurement, settings: ForwardSettings, points: MaterialPoints) -> tuple[Plan, Plan]:
    """The isotropic stage to p0 and the shear stage of ``test`` as plans of the population (module docstring)."""
    n, dim, p0, inc = points.n, points.dim, test.p0, settings.increment
    none, lateral = np.zeros(0, dtype=np.int64), np.arange(1, dim)
    iso = np.zeros((n, points.n_voigt))
    iso[:, :dim] = settings.iso_increment
    n_iso = programmes.n_increments_for(programmes.ISO_MAX_STRAIN, settings.iso_increment)
    isotropic = Plan("iso", n_iso, iso, none, np.zeros((n, 0)), np.zeros((n, 0)), stop_at_p=p0)
    shear = np.zeros((n, points.n_voigt))
    shear[:, 0] = inc
    if test.drained:
        shear[:, lateral] = -inc / lateral.size
        held = np.full((n, lateral.size), p0)
        return isotropic, Plan("shear", _n_shear(test, settings), shear, lateral, held, held, held=True)
    shear[:, lateral] = dimension(dim).undrained_lateral(inc)
    return isotropic, Plan("shear", _n_shear(test, settings), shear, none, np.zeros((n, 0)), np.zeros((n, 0)))


def simulate_points(test: Measurement, points: MaterialPoints, settings: ForwardSettings, *,
                    before_stage: Mapping[int, Callable[[MaterialPoints], None]] | None = None) -> Curves:
    """Curves of ``test`` for a population built as ``population`` builds it (one point per parameter
    set), its two ``stages`` run by the calibration's solver; ``before_stage`` as in
    ``element_test.stages.run_stages`` (stage 1: the shear)."""
    plans = stages(test, settings, points)
    history = History(sum(plan.n_increments for plan in plans), points.n, points.dim, observe=False)
    solver = StressControl(points, replace(POPULATION, rtol=settings.stress_rtol, max_iterations=settings.max_newton))
    _, fallback, failed = run_stages(solver, plans, history, before_stage=before_stage)
    shear = history.stage_index[:history.k] == 1
    start = int(np.flatnonzero(shear)[0]) - 1
    rows = np.stack([_row(history.rows[k], history.rows[start], points.dim) for k in range(start, history.k)])
    rows[:, :, failed] = np.nan
    eps1_model = settings.increment * np.arange(rows.shape[0])
    q, p, eps_v = (_sample(eps1_model, rows[:, i].T, test.eps1) for i in range(3))
    return Curves(q, p, eps_v, fallback, solver.jumps.copy(), *_rule_clips(points))


def _rule_clips(points: MaterialPoints) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the interlocking friction's and the critical-state renewal's clips (``Curves.n_clip`` and
    ``n_renewal_clip``), each shape (n,): zeros for a rule the population does not run."""
    friction = points.renewal if isinstance(points.renewal, InterlockingFriction) else None
    renewal = friction.inner if friction is not None else points.renewal
    none = np.zeros(points.n, dtype=np.int64)
    return (none if friction is None else friction.floored + friction.fallbacks,
            none if renewal is None else renewal.capped + renewal.clipped)


def _row(row: np.ndarray, start: np.ndarray, dim: int) -> np.ndarray:
    """q, p, eps_v of every point of a history row (n, dim + n_stress + 1), strains counted from ``start``, shape (3, n)."""
    eps = row[:, :dim] - start[:, :dim]
    s, record = row[:, dim:-1], dimension(dim)
    return np.stack([record.deviator(s), record.mean_stress(s), eps.sum(axis=1)])


def contact_law_at(full: Mapping[str, np.ndarray], i: int, law: str) -> Law:
    """The contact law ``law`` of parameter set ``i`` of ``full`` (``full_parameters``)."""
    if law == HertzMindlinLaw.name:
        return HertzMindlinLaw(shear_modulus=float(full["shear_modulus"][i]), poisson=float(full["poisson"][i]),
                               phi_g_deg=float(full["phi_g"][i]))
    return ContactLaw(kn=float(full["kn"][i]), kt_over_kn=float(full["kt_over_kn"][i]),
                      phi_g_deg=float(full["phi_g"][i]))


def _simulate_one_by_one(test: Measurement, full: dict[str, np.ndarray], settings: ForwardSettings) -> Curves:
    n = full["phi_g"].size
    out = np.empty((3, n, test.eps1.size))
    fallback, jumps = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    n_shear = _n_shear(test, settings)
    programme = SHEAR_TESTS[test.dim](test.p0, n_shear * settings.increment, settings.increment,
                                      iso_increment=settings.iso_increment, drained=test.drained)
    for i in range(n):
        law = contact_law_at(full, i, settings.law)
        model = make_cell_model(settings.backend, contact_law=law, radius=settings.radius, dim=test.dim,
                                **dict(settings.backend_options))
        alpha0 = float(full["alpha0"][i])
        meso = plain_h_cell(test.dim, alpha0, settings.radius)
        record = driver.run(model, programme, mesostructure=meso, n_orientations=settings.n_orientations,
                            stress_rtol=settings.stress_rtol, max_newton_iterations=settings.max_newton,
                            progress=False, lebedev_order=settings.lebedev_order, n_spins=settings.n_spins,
                            staggered_spins=settings.staggered_spins,
                            critical_state=rule_at({n: full[n][i] for n in RULE if n in full}, settings))
        shear = record.stage == programme[1].label
        start = np.flatnonzero(shear)[0] - 1
        volumetric = record.eps_v
        e11 = record.eps11[start:]
        eps1_model = e11 - e11[0]
        values = np.stack([record.q[start:], record.p[start:], volumetric[start:] - volumetric[start]])
        for c in range(3):
            out[c, i] = np.interp(test.eps1, eps1_model, values[c])
        fallback[i] = int(np.nansum(record.diagnostics.get("n_unconverged", np.zeros(1))) > 0)
        jumps[i] = int(np.nansum(record.diagnostics.get("stress_control_jump", np.zeros(1))))
    return Curves(out[0], out[1], out[2], fallback, jumps, *(np.zeros(n, dtype=np.int64) for _ in range(2)))
