"""The critical-state renewal (``homogenization.material.critical_state``) on a calibration's population.

A calibration's population is one material of n points whose cell model carries per-cell contact laws and
opening angles (``forward.population``: ``with_cell_laws``), so the package's ``Renewal`` cannot build or step
its fresh cells through that model (it expects one law for all cells and reads alpha0 from the points'
mesostructures). ``PopulationRenewal`` runs the same rule, unchanged, through a view of the material whose
model builds fresh cells touching at the asked angles (``touching_state``) and steps them with the laws of
the cells they replace; each point's initial void ratio is its own alpha0's on the map, or, for a population
with a spread of opening angles (``opening_spread``), each family's of its own angle alpha0 + spread x_j.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from types import SimpleNamespace
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization.material import opening_spread
from homogenization.material.critical_state import CriticalState, Renewal, renewal_phases
from homogenization.material.density import DensityMap
from homogenization.material.homogenised import HomogenisedMaterial, MaterialState
from warp_hcell.mesostructures.mesostructure import Mesostructure


class _FreshCells:
    """The population's cell model as ``Renewal`` sees it: fresh cells are touching cells at each
    mesostructure's angle, stepped with the contact laws of the cells whose places they take (``index``)."""

    def __init__(self, model: Any, laws: Mapping[str, np.ndarray], law: str, radius: float, cells: int) -> None:
        self._model, self._laws, self._law, self._radius, self._cells = model, laws, law, radius, cells
        self._angles: dict[int, tuple[Mesostructure, float]] = {}
        self.index = np.zeros(0, dtype=np.int64)
        """The cells (flat indices) renewed in the present increment."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self._model, name)

    def init_state(self, mesostructure: Sequence[Mesostructure], n_cells: int) -> Any:
        for m in mesostructure:
            if id(m) not in self._angles:
                self._angles[id(m)] = (m, self._model.check_mesostructure(m))  # keeps m, so its id stays its own
        angles = np.array([self._angles[id(m)][1] for m in mesostructure], dtype=np.float64)
        return self._model.touching_state(angles, int(n_cells))

    def step(self, state: Any, d_eps_local: np.ndarray, *, with_tangent: bool = False) -> Any:
        point = self.index // self._cells
        laws = {name: values[point] for name, values in self._laws.items()}
        model_class = type(self._model)
        if self._law == "hertz-mindlin":
            subset = model_class.with_hertz_cell_laws(laws["shear_modulus"], laws["poisson"], laws["phi_g"],
                                                      self._radius)
        else:
            subset = model_class.with_cell_laws(laws["kn"], laws["kt_over_kn"], laws["phi_g"], self._radius)
        return subset.step(state, d_eps_local, with_tangent=with_tangent)


class _MaterialView:
    """``material`` with its cell model replaced by ``model`` (everything else delegated)."""

    def __init__(self, material: HomogenisedMaterial, model: _FreshCells) -> None:
        self._material, self.model = material, model

    def __getattr__(self, name: str) -> Any:
        return getattr(self._material, name)


class PopulationRenewal(Renewal):
    """``Renewal`` of a calibration population (module docstring).

    Args:
        params: the rule's parameters.
        material: the population (``forward.population(...).material``), n points.
        state: its state where counting starts.
        density: the void-ratio map (its e_min and e_max replaced per point by ``e_bounds`` where given).
        alpha0_deg: each point's initial opening angle [deg], shape (n,).
        laws: the contact-law parameters of each point, name -> shape (n,) (``forward.full_parameters``).
        law: "linear" or "hertz-mindlin".
        radius: grain radius [m].
        per_point: fields of ``params`` that differ between points, name -> shape (n,) (each point's set
            checked as a ``CriticalState``); None: ``params`` for every point.
        e_bounds: each point's (e_min, e_max) [-], shapes (n,), e_min < e_max (a calibration of the map); None:
            ``density``'s.
        spread_deg: each point's spread of opening angles [deg], shape (n,) (``opening_spread``: its cells are
            ``N_NODES`` families, renewed each on its own void ratio); None: one opening angle per point.
    """

    def __init__(self, params: CriticalState, material: HomogenisedMaterial, state: MaterialState,
                 density: DensityMap, alpha0_deg: np.ndarray, laws: Mapping[str, np.ndarray], law: str,
                 radius: float, per_point: Mapping[str, np.ndarray] | None = None,
                 e_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 spread_deg: np.ndarray | None = None) -> None:
        self._fresh = _FreshCells(material.model, laws, law, radius, material.orient.n_cells)
        super().__init__(params, _MaterialView(material, self._fresh), state, density)
        n = material.n_points
        self.nonfinite = np.zeros(n, dtype=bool)
        """Per point, whether a fresh angle of it was ever not finite (``fresh_angle``)."""

        def of_points(v) -> np.ndarray:
            return np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))

        alpha0 = of_points(alpha0_deg)[:, None]
        if spread_deg is not None:
            x, _ = opening_spread.nodes()
            self.families = x.size
            if material.orient.n_cells % self.families:
                raise ValueError(f"a point of {material.orient.n_cells} cells holds no {self.families} families")
            alpha0 = alpha0 + of_points(spread_deg)[:, None] * x[None, :]
            one = material.orient.n_cells // self.families  # phases of one family's cells, the same in every family
            self.phase = np.tile(renewal_phases(np.asarray(material.orient.frames)[:one], params.phases),
                                 self.families * n)
        k = self.families
        alpha0 = alpha0.reshape(-1)
        if e_bounds is not None:
            e_min, e_max = (np.repeat(of_points(v), k) for v in e_bounds)
            if not np.all(e_min < e_max):
                raise ValueError("every point's e_min must be below its e_max")
            self.density = SimpleNamespace(e_min=e_min, e_max=e_max, alpha_dense_deg=density.alpha_dense_deg,
                                           alpha_loose_deg=density.alpha_loose_deg)
        m = self.density  # DensityMap.void_ratio on arrays
        self.e0 = m.e_max - (m.alpha_loose_deg - alpha0) / (m.alpha_loose_deg - m.alpha_dense_deg) * (m.e_max - m.e_min)
        if per_point:
            values = {name: of_points(v) for name, v in per_point.items()}
            for i in range(n):
                replace(params, **{name: float(v[i]) for name, v in values.items()}).check()
            self.params = SimpleNamespace(**{**asdict(params), **{name: np.repeat(v, k) for name, v in values.items()}})

    def set_friction(self, phi_g_deg: np.ndarray) -> None:
        """Step the fresh cells from now on with each point's friction angle ``phi_g_deg`` [deg], shape (n,)
        (``calibration.interlocking``)."""
        self._fresh._laws = {**self._fresh._laws, "phi_g": np.asarray(phi_g_deg, dtype=np.float64).copy()}

    def fresh_angle(self, J: np.ndarray) -> np.ndarray:
        """``Renewal.fresh_angle``; alpha_c where a point's J is not finite (a set whose run failed: its curves
        are NaN; counted in ``nonfinite``), so that one failed set does not stop the population."""
        angle = super().fresh_angle(J)
        bad = ~np.isfinite(angle)
        if bad.any():
            self.nonfinite = self.nonfinite | bad.reshape(self.nonfinite.size, self.families).any(axis=1)
            angle = np.where(bad, self.params.alpha_c_deg, angle)
        return angle

    def _renewed(self, cells: Any, J: np.ndarray, due: Any, *args: Any, **kwargs: Any) -> Any:
        """``Renewal._renewed``, the cells due (``due``: a mask of the cells, or a record holding it as "due")
        named to the fresh-cell model first, which steps them with their own laws."""
        self._fresh.index = np.flatnonzero(due["due"] if isinstance(due, dict) else due)
        return super()._renewed(cells, J, due, *args, **kwargs)


def laws_of(full: Mapping[str, np.ndarray], law: str) -> dict[str, np.ndarray]:
    """The contact-law parameters of ``full`` (``forward.full_parameters``) that ``PopulationRenewal`` needs."""
    names = ("shear_modulus", "poisson", "phi_g") if law == "hertz-mindlin" else ("kn", "kt_over_kn", "phi_g")
    return {name: np.asarray(full[name], dtype=np.float64) for name in names}

