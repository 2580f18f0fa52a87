"""Forward model of a calibration: the biaxial or triaxial curves of a whole population of parameter sets.

``simulate(test, params, settings)`` runs the test (isotropic compression to p0, then
constant-volume or drained shear) for n parameter sets at once and returns the model's q, p
and eps_v at the measured eps1 values. With the analytical backend the n sets are ONE
``HomogenisedMaterial`` (2D) or ``HomogenisedMaterial3D`` (triaxial tests) of n material
points, each with its own cells (``AnalyticalCell.with_cell_laws`` /
``Analytical3DCell.with_cell_laws``: per-cell kn, kt/kn, phi_g and alpha0), so every increment
is one batched ``step`` over n x (cells per point) cells. Other backends take one contact law
per model: their sets run one after the other through ``homogenization.driver.run``.

Stages, per point, as in ``homogenization.loading.biaxial`` / ``loading.triaxial``: equal strain
increments of ``iso_increment`` on every normal component until p reaches p0, the increment
that crosses it shortened (regula falsi on its scale) so that p lands on p0; then ``increment``
steps of eps11 with the lateral strains constant-volume (2D: d_eps22 = -d_eps11; 3D:
``loading.isochoric``, d_eps22 = d_eps33) or solved by Newton so that every lateral stress is p0
(drained). A point is advanced only while its stage lasts (the others keep their state), so a
point's curve does not depend on the population it runs in.

Units: stresses [N/m] (2D) or [Pa] (3D), strains [-], compression and contraction positive;
eps1 and eps_v are counted from the end of the isotropic stage. 3D: q = sqrt(3 J2), p = tr(sigma) / 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from homogenization import driver, loading, orientation as orient_mod, orientation3d
from homogenization.backends import make_cell_model
from homogenization.backends.analytical import AnalyticalCell
from homogenization.backends.analytical3d import Analytical3DCell
from homogenization.calibration.data import Measurement
from homogenization.invariants import deviator_3d, mean_stress_3d
from homogenization.material import HomogenisedMaterial, HomogenisedMaterial3D, MaterialState
from warp_hcell.core.parameters import CellDefaults, ContactLaw, LoadingDefaults
from warp_hcell.mesostructures.hcell import build_h_cell_3d, h_cell

PARAMETERS = ("phi_g", "kn", "kt_over_kn", "alpha0")
"""Names of the calibratable parameters, in the units of the CLI flags: phi_g [deg], kn [N/m],
kt_over_kn [-], alpha0 [deg]."""


@dataclass(frozen=True)
class ForwardSettings:
    """Numerical settings of the forward model.

    Attributes:
        backend: "analytical" (batched), "dem" or "ann" (one parameter set at a time).
        n_orientations: cell orientations per material point of a 2D test [-].
        lebedev_order, n_spins: cell orientations of a triaxial test (``orientation3d.orientations_3d``);
            11 x 4 = 100 cells, coarser than ``hmodel triaxial``'s default (as 36 orientations are in
            2D) so that a population of parameter sets runs in minutes; its quadrature error is in
            docs/triaxial.md (Quadrature).
        staggered_spins: stagger the spins from axis to axis (``orientation3d``); False here: on
            100 cells aligned spins keep the rule's cube symmetry (sigma22 = sigma33 on the
            axisymmetric tests), where staggered ones would leave a quadrature asymmetry of about
            1 % of p, and the forward model's bias in docs/calibration.md was measured on them.
        increment: axial strain increment of the shear stage [-].
        iso_increment: strain increment per component of the isotropic stage [-].
        radius: grain radius [m].
        stress_rtol: relative tolerance of p = p0 (landing) and sigma22 = p0 (drained) [-].
        max_newton: Newton iterations allowed per drained increment [-].
        fixed: value of every parameter not calibrated (CLI flag units).
        backend_options: extra keyword options of the backend (dem/ann: device, threads, model).
    """

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
        "alpha0": CellDefaults.alpha0_deg})
    backend_options: Mapping[str, object] = field(default_factory=dict)


@dataclass
class Curves:
    """Model curves of n parameter sets at a test's eps1 values, each shape (n, n_data).

    ``q``, ``p`` [N/m in 2D, Pa in 3D], ``eps_v`` [-]; NaN for a point whose isotropic stage does not reach p0
    within ``homogenization.loading.ISO_MAX_STRAIN`` (too soft); ``n_fallback``: per point, the
    isotropic landings and drained Newton iterations that did not meet ``stress_rtol`` (their last
    iterate is used), or (dem/ann, one set at a time) 1 where the backend reported unconverged
    cells, shape (n,).
    """

    q: np.ndarray
    p: np.ndarray
    eps_v: np.ndarray
    n_fallback: np.ndarray

    def channel(self, name: str) -> np.ndarray:
        """The curve of ``name`` ("q", "p" or "eps_v")."""
        return getattr(self, name)


def full_parameters(params: Mapping[str, np.ndarray], settings: ForwardSettings) -> dict[str, np.ndarray]:
    """All four parameters as arrays of one shape (n,): the calibrated ones, the others fixed."""
    n = len(np.atleast_1d(next(iter(params.values())))) if params else 1
    return {name: np.broadcast_to(np.asarray(params.get(name, settings.fixed[name]), dtype=np.float64), (n,)).copy()
            for name in PARAMETERS}


def simulate(test: Measurement, params: Mapping[str, np.ndarray], settings: ForwardSettings) -> Curves:
    """Curves of ``test`` for each parameter set; ``params`` maps names of ``PARAMETERS`` to shape (n,).

    Raises:
        ValueError: a parameter value outside its range (one line).
        homogenization.driver.ControlError: (dem/ann) a stage that cannot be run (p0 not reached).
    """
    full = full_parameters(params, settings)
    if settings.backend == "analytical":
        return _simulate_batched(test, full, settings)
    return _simulate_one_by_one(test, full, settings)


def _n_shear(test: Measurement, settings: ForwardSettings) -> int:
    return max(1, math.ceil(float(test.eps1.max()) / settings.increment - 1e-9))


def _sample(eps1_model: np.ndarray, values: np.ndarray, eps1: np.ndarray) -> np.ndarray:
    """Linear interpolation of values (n, m) given on eps1_model (m,) at eps1 (k,)."""
    j = np.clip(np.searchsorted(eps1_model, eps1, side="right") - 1, 0, eps1_model.size - 2)
    w = (eps1 - eps1_model[j]) / (eps1_model[j + 1] - eps1_model[j])
    return values[:, j] * (1.0 - w) + values[:, j + 1] * w


class _Population:
    """Material points of a population with per-point cells, in 2D (Voigt 11, 22, 12) or 3D
    (11, 22, 33, 23, 13, 12); advances a subset of points at a time."""

    def __init__(self, full: dict[str, np.ndarray], settings: ForwardSettings, dim: int) -> None:
        n = full["kn"].size
        if dim == 2:
            orient = orient_mod.orientations(settings.n_orientations)
            cell_class, material_class, meso = AnalyticalCell, HomogenisedMaterial, h_cell(CellDefaults.alpha0_deg,
                                                                                           settings.radius)
        else:
            orient = orientation3d.orientations_3d(settings.lebedev_order, settings.n_spins,
                                                   staggered=settings.staggered_spins)
            cell_class, material_class = Analytical3DCell, HomogenisedMaterial3D
            meso = build_h_cell_3d(CellDefaults.alpha0_deg, radius=settings.radius)
        self.n_orientations = int(np.size(orient.weights))
        per_cell = {name: np.repeat(values, self.n_orientations) for name, values in full.items()}
        model = cell_class.with_cell_laws(per_cell["kn"], per_cell["kt_over_kn"], per_cell["phi_g"],
                                          settings.radius, alpha0_deg=per_cell["alpha0"])
        self.model = model
        self.material = material_class(model, orient, meso, n)
        self.state = self.material.init_state()
        self.n = n
        self.dim = dim
        self.n_components = 3 if dim == 2 else 6

    def p(self, stress: np.ndarray) -> np.ndarray:
        """Mean normal stress of stresses (n, n_components) [N/m or Pa]."""
        return stress[:, :self.dim].mean(axis=1)

    def trial(self, d_e: np.ndarray, with_tangent: bool = False):
        return self.material.update(self.state, d_e, with_tangent=with_tangent)

    def accept(self, update, mask: np.ndarray) -> None:
        """Take ``update`` for the points of ``mask`` (n,), keep the others."""
        old, new = self.state, update.state
        cells_mask = np.repeat(mask, self.n_orientations)
        old_arrays = self.model.state_to_arrays(old.cells)
        new_arrays = self.model.state_to_arrays(new.cells)
        cells = self.model.state_from_arrays(
            {k: np.where(cells_mask, new_arrays[k], old_arrays[k]) for k in old_arrays})
        self.state = MaterialState(cells, np.where(mask, new.J, old.J), np.where(mask[:, None], new.strain, old.strain),
                                   np.where(mask[:, None], new.stress, old.stress))


def _simulate_batched(test: Measurement, full: dict[str, np.ndarray], settings: ForwardSettings) -> Curves:
    pop = _Population(full, settings, test.dim)
    n = pop.n
    p0, rtol = test.p0, settings.stress_rtol
    fallback = np.zeros(n, dtype=np.int64)
    # isotropic stage
    iso = settings.iso_increment
    d_iso = np.zeros((n, pop.n_components))
    d_iso[:, :pop.dim] = iso
    active = np.ones(n, dtype=bool)
    for _ in range(loading.n_increments_for(loading.ISO_MAX_STRAIN, iso)):
        update = pop.trial(d_iso)
        p_new = pop.p(update.stress)
        crossing = active & (p_new >= p0)
        pop.accept(update, active & ~crossing)
        if crossing.any():
            fallback += _land(pop, crossing, d_iso, update, p0, rtol, settings.max_newton)
        active &= ~crossing
        if not active.any():
            break
    failed = active
    strain0 = pop.state.strain.copy()
    n_shear = _n_shear(test, settings)
    inc = settings.increment
    rows = np.empty((n_shear + 1, 3, n))  # q, p, eps_v
    rows[0] = _row(pop.state, strain0)
    tangent = None
    undrained = np.zeros((n, pop.n_components))
    undrained[:, 0] = inc
    undrained[:, 1:pop.dim] = -inc if pop.dim == 2 else 1.0 - 1.0 / math.sqrt(1.0 - inc)  # loading.isochoric
    for k in range(n_shear):
        if test.drained:
            tangent, fails = _drained_increment(pop, inc, p0, rtol, settings.max_newton, tangent)
            fallback += fails
        else:
            pop.accept(pop.trial(undrained), np.ones(n, dtype=bool))
        rows[k + 1] = _row(pop.state, strain0)
    eps1_model = inc * np.arange(n_shear + 1)
    rows[:, :, failed] = np.nan
    q, p, eps_v = (_sample(eps1_model, rows[:, i].T, test.eps1) for i in range(3))
    return Curves(q, p, eps_v, fallback)


def _row(state: MaterialState, strain0: np.ndarray) -> np.ndarray:
    """q, p, eps_v of every point, shape (3, n)."""
    s = state.stress
    eps = state.strain - strain0
    if s.shape[1] == 3:
        return np.stack([s[:, 0] - s[:, 1], 0.5 * (s[:, 0] + s[:, 1]), eps[:, 0] + eps[:, 1]])
    return np.stack([deviator_3d(*s.T), mean_stress_3d(s[:, 0], s[:, 1], s[:, 2]), eps[:, :3].sum(axis=1)])


def _land(pop: _Population, crossing: np.ndarray, d_iso: np.ndarray, over, p0: float, rtol: float,
          max_iterations: int) -> np.ndarray:
    """Shorten the crossing increment of the points of ``crossing`` so that p = p0 (Illinois).

    ``over`` is the trial update of the whole increment ``d_iso`` (n, 3). Returns, per point, 1
    where the tolerance was not met (the last iterate is taken), else 0."""
    p_old = pop.p(pop.state.stress)
    p_over = pop.p(over.stress)
    lo, f_lo = np.zeros(pop.n), p_old - p0
    hi, f_hi = np.ones(pop.n), p_over - p0
    side = np.zeros(pop.n)
    todo = crossing & (p_over - p0 > rtol * p0)
    pop.accept(over, crossing & ~todo)
    for _ in range(max_iterations):
        if not todo.any():
            return np.zeros(pop.n, dtype=np.int64)
        lam = np.where(todo, (lo * f_hi - hi * f_lo) / np.where(todo, f_hi - f_lo, 1.0), 1.0)
        update = pop.trial(d_iso * lam[:, None])
        f = pop.p(update.stress) - p0
        done = todo & (np.abs(f) <= rtol * p0)
        pop.accept(update, done)
        above = todo & ~done & (f > 0.0)
        below = todo & ~done & (f <= 0.0)
        f_lo = np.where(above & (side == 1), 0.5 * f_lo, f_lo)
        f_hi = np.where(below & (side == -1), 0.5 * f_hi, f_hi)
        hi, f_hi = np.where(above, lam, hi), np.where(above, f, f_hi)
        lo, f_lo = np.where(below, lam, lo), np.where(below, f, f_lo)
        side = np.where(above, 1.0, np.where(below, -1.0, side))
        todo &= ~done
    pop.accept(update, todo)
    return todo.astype(np.int64)


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x of a x = b per point, a (n, k, k), b (n, k), k = 1 or 2, by Cramer's rule: a singular a
    gives inf or NaN (that point's Newton then fails its tolerance) rather than an exception."""
    if a.shape[1] == 1:
        return b / a[:, :, 0]
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    return np.stack([b[:, 0] * a[:, 1, 1] - b[:, 1] * a[:, 0, 1], a[:, 0, 0] * b[:, 1] - a[:, 1, 0] * b[:, 0]],
                    axis=1) / det[:, None]


def _drained_increment(pop: _Population, inc: float, p0: float, rtol: float, max_iterations: int,
                       tangent: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """One drained increment of every point: d_eps11 = inc, the k = dim - 1 lateral strain
    increments by Newton on sigma_lateral = p0 (sigma22; 3D: sigma22 and sigma33).

    Returns the last tangent d sigma_lateral / d(d_eps11, d_eps_lateral) of each point, shape
    (n, k, 1 + k), and 1 where Newton did not meet the tolerance (the last iterate is taken).
    A point whose residual is not finite (its iteration overflowed, or its state is NaN from an
    earlier increment) stops iterating at once and takes that iterate: every later iterate
    would be NaN too, so its curve is the same, without max_iterations population updates per
    increment for the rest of the stage."""
    n, lat = pop.n, np.arange(1, pop.dim)
    k = lat.size
    columns = np.concatenate([[0], lat])
    d = np.zeros((n, pop.n_components))
    d[:, 0] = inc
    if tangent is None:
        d[:, lat] = -inc / k
    else:
        d[:, lat] = _solve(tangent[:, :, 1:], p0 - pop.state.stress[:, lat] - tangent[:, :, 0] * inc)
    todo = np.ones(n, dtype=bool)
    gave_up = np.zeros(n, dtype=bool)
    tangent = np.zeros((n, k, 1 + k)) if tangent is None else tangent.copy()
    for _ in range(max_iterations):
        update = pop.trial(d, with_tangent=True)
        r = update.stress[:, lat] - p0
        tangent = np.where(todo[:, None, None], update.tangent[:, lat][:, :, columns], tangent)
        done = todo & np.all(np.abs(r) <= rtol * p0, axis=1)
        lost = todo & ~np.all(np.isfinite(r), axis=1)
        pop.accept(update, done | lost)
        gave_up |= lost
        todo &= ~(done | lost)
        if not todo.any():
            return tangent, gave_up.astype(np.int64)
        identity = np.broadcast_to(np.eye(k), tangent[:, :, 1:].shape)
        step = _solve(np.where(todo[:, None, None], tangent[:, :, 1:], identity), r)
        d[:, lat] = np.where(todo[:, None], d[:, lat] - step, d[:, lat])
    pop.accept(update, todo)
    return tangent, (todo | gave_up).astype(np.int64)


def _simulate_one_by_one(test: Measurement, full: dict[str, np.ndarray], settings: ForwardSettings) -> Curves:
    n = full["kn"].size
    out = np.empty((3, n, test.eps1.size))
    fallback = np.zeros(n, dtype=np.int64)
    n_shear = _n_shear(test, settings)
    if test.dim == 2:
        programme = loading.biaxial(test.p0, n_shear * settings.increment, settings.increment,
                                    iso_increment=settings.iso_increment, drained=test.drained)
    else:
        programme = loading.triaxial(test.p0, n_shear * settings.increment, settings.increment,
                                     test="drained" if test.drained else "undrained",
                                     iso_increment=settings.iso_increment)
    for i in range(n):
        law = ContactLaw(kn=float(full["kn"][i]), kt_over_kn=float(full["kt_over_kn"][i]),
                         phi_g_deg=float(full["phi_g"][i]))
        model = make_cell_model(settings.backend, contact_law=law, radius=settings.radius, dim=test.dim,
                                **dict(settings.backend_options))
        alpha0 = float(full["alpha0"][i])
        meso = (h_cell(alpha0, settings.radius) if test.dim == 2
                else build_h_cell_3d(alpha0, radius=settings.radius))
        record = driver.run(model, programme, mesostructure=meso, n_orientations=settings.n_orientations,
                            stress_rtol=settings.stress_rtol, max_newton_iterations=settings.max_newton,
                            progress=False, lebedev_order=settings.lebedev_order, n_spins=settings.n_spins,
                            staggered_spins=settings.staggered_spins)
        shear = record.stage == programme[1].label
        start = np.flatnonzero(shear)[0] - 1
        volumetric = record.eps11 + record.eps22 + (record.eps33 if test.dim == 3 else 0.0)
        e11 = record.eps11[start:]
        eps1_model = e11 - e11[0]
        values = np.stack([record.q[start:], record.p[start:], volumetric[start:] - volumetric[start]])
        for c in range(3):
            out[c, i] = np.interp(test.eps1, eps1_model, values[c])
        fallback[i] = int(np.nansum(record.diagnostics.get("n_unconverged", np.zeros(1))) > 0)
    return Curves(out[0], out[1], out[2], fallback)
