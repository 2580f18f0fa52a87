"""Renewal of a material point's cells towards a critical state (opt-in: ``CriticalState``).

Cells of a point are replaced by fresh, touching cells of the same orientations, built by the backend's
own ``init_state`` (closed form, DEM and ANN share the rule exactly). The clock is the point's
distortion: per increment, s = sum_k w_k sum_{a<b} abs(d eps_a - d eps_b) / sum_k w_k (the cells'
local normal strains, so an isotropic compression renews nothing); cell k is renewed each time
floor(S_k + phi_k) grows, S_k the sum of lambda s over the increments and phi_k = frac(j g) a fixed
phase (g the golden ratio, j the index of k's class of cells sharing a phase, ``PHASES``).

With ``in_increment`` a renewal is made in every trial of the increment where it falls due: which cells
fall due, and where in the increment, come from the previous increment's tick (fixed over the trials, so
the stress stays continuous in the trial increment); each fresh cell is stepped by the rest of the
increment after its last renewal, and the tangent is corrected. Otherwise fresh cells are force-free,
made after the recorded increment.

Both the rate lambda and the fresh cells' opening angle follow the point's current void ratio
e = (1 + e0) J - 1 (``homogenization.material.density``'s map, a(e) the opening angle the map gives
e, extrapolated linearly): lambda = min(rate exp(rate_gain (a(e) - alpha_c)), rate_max) (``rate_gain_loose`` where a(e) > alpha_c) and
alpha_f = clip(alpha_c + gain (a(e) - alpha_c), alpha_min, alpha_max). A point looser than alpha_c
renews faster with looser, contractive cells, a denser one slower with denser, dilatant cells, so
loose and dense points head for one stationary void ratio at each pressure. A point whose cells fall in families
of initial opening angles (``opening_spread``) renews each family on its own void ratio, e0 the map's of the
family's angle (J and the strain shared): a mixture of denser and looser sub-volumes. ``Renewal`` counts the
renewals, the capped rates, the clipped angles and the renewals merged into one (more than one renewal
of a cell fell due in an increment).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from homogenization.material.density import DensityMap, current_void_ratio, default_map, line_angle_deg
from homogenization.material.homogenised import HomogenisedMaterial, MaterialState, MaterialUpdate
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures import hcell
from warp_hcell.mesostructures.mesostructure import Mesostructure

PHASES = ("cell", "axis", "mirror", "mirror-spin")
"""Cells that share a renewal phase: "cell": cells whose frames reflections of the macro axes map onto one another;
"axis": the spins of one axis; "mirror": the spins of axes that such reflections map onto one another;
"mirror-spin": as "mirror", one phase per spin index (the rank of a cell among its axis' cells)."""
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
"""Fractional part of the golden ratio: the cells' renewal phases are frac(k GOLDEN) [-]."""
ANGLE_STEP_DEG = 0.01
"""Fresh opening angles are rounded to this step [deg] (one mesostructure per rounded angle)."""


@dataclass(frozen=True)
class CriticalState:
    """Parameters of the renewal rule (module docstring).

    Attributes:
        rate: renewals per unit of a cell's accumulated distortion at alpha_c [-], > 0.
        gain: feedback of the point's density on the fresh cells' opening angle [-], >= 0.
        alpha_c_deg: the opening angle [deg] where neither feedback acts (in [alpha_min, alpha_max]).
        rate_gain: feedback of the point's density on the rate [1/deg], >= 0.
        rate_gain_loose: the same where a(e) > alpha_c (None: ``rate_gain``) [1/deg], >= 0.
        rate_max: cap of the rate [-], >= rate.
        alpha_min_deg: smallest fresh opening angle [deg].
        alpha_max_deg: largest fresh opening angle [deg], > alpha_min_deg.
        in_increment: renewals made inside the trials of their increment (``Renewal.within``), so that a
            cell's age does not depend on the increment; False: force-free after the recorded increment.
        phases: which cells share a renewal phase (``PHASES``).
    The defaults are ``DEFAULTS[3]``'s.
    """

    rate: float = 20.0
    gain: float = 3.0
    alpha_c_deg: float = 53.0
    rate_gain: float = 1.4
    rate_gain_loose: float | None = None
    rate_max: float = 1000.0
    alpha_min_deg: float = 46.0
    alpha_max_deg: float = 62.0
    in_increment: bool = True
    phases: str = "cell"

    def check(self) -> None:
        """ValueError (one line) for a parameter out of range."""
        if self.phases not in PHASES:
            raise ValueError(f"critical-state phases = {self.phases!r} must be one of {', '.join(PHASES)}")
        if not (math.isfinite(self.rate) and self.rate > 0.0):
            raise ValueError(f"critical-state rate = {self.rate:g} must be finite and > 0")
        if not (math.isfinite(self.rate_gain) and self.rate_gain >= 0.0):
            raise ValueError(f"critical-state rate_gain = {self.rate_gain:g} must be finite and >= 0")
        if self.rate_gain_loose is not None and not (math.isfinite(self.rate_gain_loose) and self.rate_gain_loose >= 0.0):
            raise ValueError(f"critical-state rate_gain_loose = {self.rate_gain_loose:g} must be finite and >= 0")
        if not (math.isfinite(self.rate_max) and self.rate_max >= self.rate):
            raise ValueError(f"critical-state rate_max = {self.rate_max:g} must be finite and >= rate = {self.rate:g}")
        if not (math.isfinite(self.alpha_c_deg) and self.alpha_min_deg <= self.alpha_c_deg <= self.alpha_max_deg):
            raise ValueError(f"critical-state alpha_c_deg = {self.alpha_c_deg:g} must lie in [alpha_min_deg, "
                             f"alpha_max_deg] = [{self.alpha_min_deg:g}, {self.alpha_max_deg:g}]")
        if not (math.isfinite(self.gain) and self.gain >= 0.0):
            raise ValueError(f"critical-state gain = {self.gain:g} must be finite and >= 0")
        if not (math.isfinite(self.alpha_min_deg) and math.isfinite(self.alpha_max_deg)
                and 0.0 < self.alpha_min_deg < self.alpha_max_deg < 90.0):
            raise ValueError(f"critical-state alpha_min_deg = {self.alpha_min_deg:g} and alpha_max_deg = "
                             f"{self.alpha_max_deg:g} must satisfy 0 < alpha_min < alpha_max < 90 deg")


DEFAULTS = {2: CriticalState(rate=160.0, gain=8.0, alpha_c_deg=52.0, rate_gain=1.0, rate_gain_loose=0.7, rate_max=2000.0,
                             alpha_min_deg=40.0, alpha_max_deg=58.0),
            3: CriticalState()}
"""The rule's parameters by cell dimension, chosen by measurement on the plain cells at the default contact law
and void-ratio map (docs/studies/critical_state_mechanism.md); the gains are per degree of the map's angles."""


def renewal_phases(frames: np.ndarray, rule: str = "cell") -> np.ndarray:
    """Renewal phase phi_k = frac(j g) [-] of each cell, shape (N,), of frames R_k (N, d, d) (first column the cell's
    axis): j indexes the classes of cells that share a phase under ``rule`` (``PHASES``; "cell": abs(R_k) agree to
    1e-9), in order of first appearance; such cells are renewed together."""
    axis = np.round(frames[:, :, 0], 9)
    if rule == "cell":
        keys = np.abs(frames).reshape(frames.shape[0], -1)
    elif rule == "axis":
        keys = axis
    else:
        keys = np.abs(frames[:, :, 0])
        if rule == "mirror-spin":
            _, same = np.unique(axis, axis=0, return_inverse=True)
            same = same.reshape(-1)
            order = np.argsort(same, kind="stable")
            start = np.searchsorted(same[order], same[order])
            spin = np.empty(same.size)
            spin[order] = np.arange(same.size) - start
            keys = np.column_stack([keys, spin])
    keys = np.round(keys, 9)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return np.mod(order[inverse.reshape(-1)] * GOLDEN, 1.0)


def _plain(meso: Mesostructure) -> tuple[float, float]:
    """(alpha0_deg, radius) of a plain H-cell of either dimension; ValueError (one line) for another cell."""
    plain = hcell.plain_alpha0(meso) if meso.dim == 2 else hcell.plain_alpha0_3d(meso)
    if plain is None:
        raise ValueError(f"the critical-state renewal builds fresh plain H-cells; mesostructure {meso.name!r} is not one")
    return plain


class Renewal:
    """The renewal rule applied to the points of one ``HomogenisedMaterial`` (module docstring).

    Args:
        params: the rule's ``CriticalState`` (checked here).
        material: the material whose cells are renewed; every point's mesostructure a plain H-cell.
        state: the material's state where counting starts (its strain is the reference).
        density: the void-ratio map (None: ``density.default_map`` of the cells' dimension).

    Raises:
        ValueError: (one line) bad parameters, a mesostructure that is not a plain H-cell, or an
            ``alpha_min_deg`` below the cell's smallest opening angle.
    """

    def __init__(self, params: CriticalState, material: HomogenisedMaterial, state: MaterialState,
                 density: DensityMap | None = None) -> None:
        params.check()
        floor = dimension(material.dim).min_opening_deg
        if floor is not None and params.alpha_min_deg < floor:
            raise ValueError(f"critical-state alpha_min_deg = {params.alpha_min_deg:g} deg is below "
                             f"{floor:g} deg, the {material.dim}D cell's smallest opening angle")
        self.params, self.material = params, material
        self.density = default_map(material.dim) if density is None else density
        plains = [_plain(meso) for meso in material.mesostructures]
        self.radius = plains[0][1]
        alpha0 = np.array([plains[i][0] for i in material.point_mesostructure])
        self.e0 = np.array([self.density.void_ratio(a) for a in alpha0])
        """Each family's initial void ratio [-] (the map's), shape (n_points * families,), point-major."""
        self.families = 1
        """Families of opening angles per point [-]: each point's cells are ``families`` runs of n_cells / families
        cells (family-major, ``opening_spread.replicate``), each family renewed on its own void ratio
        (``calibration.renewal.PopulationRenewal`` with a spread; here 1)."""
        n = material.orient.n_cells
        self.phase = np.tile(renewal_phases(np.asarray(material.orient.frames), params.phases), material.n_points)
        """phi_k [-] of every cell (``renewal_phases``), shape (n_cells,)."""
        self.distortion = np.zeros(material.n_cells)
        """Renewal clock of every cell: its distortion times the rate, summed [-], shape (n_cells,)."""
        self.count = np.zeros(material.n_points, dtype=np.int64)
        """Renewals made per point."""
        self.merged = np.zeros(material.n_points, dtype=np.int64)
        """Per point, renewals that fell due in an increment where the cell was already due (made once): more
        than one renewal per cell and increment, i.e. an increment too large for the rate."""
        self.capped = np.zeros(material.n_points, dtype=np.int64)
        """Per point, the increments (times families) whose rate ``rate_max`` capped."""
        self.clipped = np.zeros(material.n_points, dtype=np.int64)
        """Per point, the fresh cells whose opening angle [alpha_min_deg, alpha_max_deg] clipped."""
        self.log: list[tuple[np.ndarray, ...]] = []
        """(count, capped, clipped, merged) after each ``advance`` call (one per recorded increment)."""
        self.last_strain = np.array(state.strain)
        self.next_tick = np.zeros(material.n_cells)
        """Clock tick of every cell over the next increment (``in_increment``): the last accepted increment's."""
        self._mesos: dict[float, Mesostructure] = {}

    def _meso(self, alpha_deg: float) -> Mesostructure:
        key = round(float(alpha_deg) / ANGLE_STEP_DEG) * ANGLE_STEP_DEG
        if key not in self._mesos:
            self._mesos[key] = hcell.plain_h_cell(self.material.dim, key, self.radius)
        return self._mesos[key]

    def density_angle(self, J: np.ndarray) -> np.ndarray:
        """a(e) [deg]: the opening angle that the map gives each family's current void ratio e = (1 + e0) J - 1 (J
        [-] per point, shape (n_points,)), extrapolated linearly beyond [e_min, e_max], shape (n_points * families,)."""
        m, J = self.density, np.repeat(np.asarray(J, dtype=np.float64), self.families)
        return line_angle_deg(current_void_ratio(self.e0, J), m.e_min, m.e_max, m.alpha_dense_deg, m.alpha_loose_deg)

    def fresh_angle(self, J: np.ndarray) -> np.ndarray:
        """Opening angle alpha_f [deg] of fresh cells of each family of the points of volume ratio J [-] (n_points,)
        before the clip to [alpha_min_deg, alpha_max_deg], shape (n_points * families,)."""
        p = self.params
        return p.alpha_c_deg + p.gain * (self.density_angle(J) - p.alpha_c_deg)

    def rate(self, J: np.ndarray) -> np.ndarray:
        """Renewals per unit distortion [-] of each family of the points of volume ratio J [-] (n_points,) before the
        cap ``rate_max``, shape (n_points * families,)."""
        p = self.params
        excess = self.density_angle(J) - p.alpha_c_deg
        loose = p.rate_gain if p.rate_gain_loose is None else p.rate_gain_loose
        return p.rate * np.exp(np.where(excess > 0.0, loose, p.rate_gain) * excess)

    def distortion_increment(self, strain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(per-cell local increments (n_cells, dim), per-point distortion s (n_points,), module docstring) of an
        increment from the last advanced state to ``strain`` (n_points, n_voigt)."""
        d_local = self.material.localise(strain - self.last_strain)
        dim = d_local.shape[1]
        cell = sum(np.abs(d_local[:, a] - d_local[:, b]) for a in range(dim) for b in range(a + 1, dim))
        n = self.material.orient.n_cells
        weights = self.material.orient.weights
        # a sum per point, not BLAS's matrix-vector product (whose order depends on the number of points)
        return d_local, (cell.reshape(self.material.n_points, n) * weights).sum(axis=1) / weights.sum()

    def _tick(self, strain: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(per-cell local increments (n_cells, dim), per-family rates before the cap (n_points * families,),
        per-cell clock ticks (n_cells,)) of an increment from the last advanced state to ``strain`` (n_points,
        n_voigt), rates at ``J`` (n_points,)."""
        d_local, increment = self.distortion_increment(strain)
        rate = self.rate(J)
        k = self.families
        tick = np.minimum(rate, self.params.rate_max) * np.repeat(increment, k)
        return d_local, rate, np.repeat(tick, self.material.orient.n_cells // k)

    def _due(self, tick: np.ndarray) -> dict:
        """Clock before and after a tick (n_cells,), the due cells and the fraction of the increment after each due
        cell's last renewal (pure)."""
        clock0 = self.distortion + self.phase
        clock = clock0 + tick
        before, after = np.floor(clock0), np.floor(clock)
        due = after > before
        rest = np.clip((clock - after) / np.where(due, tick, 1.0), 0.0, 1.0)
        return {"distortion": self.distortion + tick, "before": before, "after": after, "due": due, "rest": rest}

    def cell_fresh_angle(self, J: np.ndarray, index: np.ndarray) -> np.ndarray:
        """The opening angle [deg] that the cells ``index`` (flat indices, shape (m,)) are renewed at: their family's
        fresh angle at volume ratio J (n_points,), clipped to [alpha_min_deg, alpha_max_deg], shape (m,)."""
        per_family = self.material.orient.n_cells // self.families
        return np.clip(self.fresh_angle(J), self.params.alpha_min_deg, self.params.alpha_max_deg)[index // per_family]

    def _renewed(self, cells, J: np.ndarray, due: np.ndarray, rest: np.ndarray | None, d_local: np.ndarray,
                 with_tangent: bool = False):
        """(``cells`` with the ``due`` cells (n_cells,) replaced by fresh ones at the points' current fresh angle,
        stepped by ``rest`` (n_cells,) times their increment ``d_local`` (None: force-free); with ``with_tangent``
        the fresh cells' d stress / d(d_local), shape (n_due, dim, dim), else None)."""
        index = np.flatnonzero(due)
        alpha = self.cell_fresh_angle(J, index)
        model = self.material.model
        angles, which = np.unique(alpha, return_inverse=True)  # one mesostructure per distinct angle
        mesos = [self._meso(a) for a in angles]
        fresh_cells = model.init_state([mesos[i] for i in which.reshape(-1)], index.size)
        tangent = None
        if rest is not None and with_tangent:
            fresh_cells, response = model.step(fresh_cells, rest[index, None] * d_local[index], with_tangent=True)
            dim = self.material.dim
            tangent = np.asarray(response.tangent).reshape(index.size, dim, dim) * rest[index, None, None]
        elif rest is not None:
            fresh_cells, _ = model.step(fresh_cells, rest[index, None] * d_local[index])
        fresh = model.state_to_arrays(fresh_cells)
        arrays = {k: np.array(v, copy=True) for k, v in model.state_to_arrays(cells).items()}
        for k, v in arrays.items():
            v[index] = fresh[k]
        return model.state_from_arrays(arrays), tangent

    def within(self, start: MaterialState, update: MaterialUpdate) -> MaterialUpdate:
        """The trial ``update`` from the last advanced state ``start`` with the renewals of its increment made
        (``in_increment``; otherwise ``update`` itself); pure. The due cells and where in the increment they fall
        due come from the previous increment's tick (fixed over the trials, so the stress stays continuous in the
        trial increment); each fresh cell is stepped by its rest of the trial's increment, and a tangent is
        corrected for the cells replaced."""
        if not self.params.in_increment:
            return update
        due = self._due(self.next_tick)
        if not due["due"].any():
            return update
        state = update.state
        d_local = self.material.localise(state.strain - self.last_strain)
        cells, fresh_tangent = self._renewed(state.cells, state.J, due["due"], due["rest"], d_local,
                                             with_tangent=update.tangent is not None)
        stress = self.material.stress_of(cells, state.J)
        tangent = update.tangent
        if tangent is not None:
            model, index = self.material.model, np.flatnonzero(due["due"])
            arrays = model.state_to_arrays(start.cells)
            old = model.state_from_arrays({k: np.array(v[index]) for k, v in arrays.items()})
            _, response = model.step(old, d_local[index], with_tangent=True)
            C = np.zeros((self.material.n_cells, self.material.dim, self.material.dim))
            C[index] = fresh_tangent - np.asarray(response.tangent).reshape(index.size, self.material.dim,
                                                                              self.material.dim)
            n = self.material.orient.n_cells
            V = self.material.V0 * np.asarray(state.J, dtype=np.float64)
            d_e = state.strain - start.strain
            volume = np.zeros_like(d_e)
            volume[:, :self.material.dim] = 1.0 / (1.0 - d_e[:, :self.material.dim])
            tangent = (tangent + self.material._cell_tangent_average(C.reshape(self.material.n_points, n,
                       self.material.dim, self.material.dim)) / V[:, None, None]
                       + (stress - update.stress)[:, :, None] * volume[:, None, :])
        return MaterialUpdate(MaterialState(cells, state.J, state.strain, stress), stress, tangent,
                              update.diagnostics)

    def advance(self, state: MaterialState) -> MaterialState:
        """Move the clock over the accepted increment ending at ``state`` and count its renewals; with
        ``in_increment`` ``state`` (renewed in ``within``) is returned and the next increment's tick set from
        this one, otherwise ``state`` with its due cells renewed force-free and its stress recomputed."""
        d_local, rate, tick = self._tick(state.strain, state.J)
        due = self._due(self.next_tick if self.params.in_increment else tick)
        self.last_strain = np.array(state.strain)
        self.next_tick = tick
        n_points, n, k = self.material.n_points, self.material.orient.n_cells, self.families
        self.capped = self.capped + (rate > self.params.rate_max).reshape(n_points, k).sum(axis=1)
        self.distortion = due["distortion"]
        self.merged = self.merged + np.maximum(due["after"] - due["before"] - 1.0, 0.0).reshape(n_points, n).sum(
            axis=1).astype(np.int64)
        per_family = due["due"].reshape(n_points * k, n // k).sum(axis=1)
        self.count = self.count + per_family.reshape(n_points, k).sum(axis=1)
        angle = self.fresh_angle(state.J)
        clipped = (angle < self.params.alpha_min_deg) | (angle > self.params.alpha_max_deg)
        self.clipped = self.clipped + (per_family * clipped).reshape(n_points, k).sum(axis=1)
        self.log.append((self.count, self.capped, self.clipped, self.merged))
        if self.params.in_increment or not due["due"].any():
            return state
        cells, _ = self._renewed(state.cells, state.J, due["due"], None, d_local)
        return MaterialState(cells, state.J, state.strain, self.material.stress_of(cells, state.J))
