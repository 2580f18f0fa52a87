"""Rollout error of the meso-ANN along whole held-out DEM paths of single cells.

A path is an isotropic precompression eps_iso followed by a proportional leg d_eps =
delta * a per increment of a macro axial strain delta, to eps1 = ``EPS_MAX``. The legs are
those a cell whose axis n makes the angle theta with the macro axis 1 sees under the macro
strain rate diag(1, b[, b]) (c = cos theta, s = sin theta): a = (c^2 + b s^2, s^2 + b c^2) for a
planar cell, a = (c^2 + b s^2, s^2 + b c^2, b) for a spatial one (t1 in the plane of n and axis
1, t2 along axis 3). ``LATERAL_RATES`` gives b: the constant-volume (isochoric) test, b = -1 in
2D and -1/2 in 3D, and a drained test of volumetric rate 1/2 of the axial one, b = -1/2 in 2D and
-1/4 in 3D.
None of these precompressions is a training path's. The DEM cell (``warp_hcell.dem.cell``),
stepped with the same increments, gives the reference; the ANN is rolled out recurrently. The
error of a path is max over the path of ``|S_ann - S_dem|`` (the diagonal components) divided by
the path's largest ``|S_dem|`` component (the path's largest force times its lever arm):
a fraction that a model returning zeros fails with 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from training.network import MesoNet
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.core.parameters import ContactLaw, DemSettings

PRECOMPRESSION = (1.5e-3, 2e-2)
"""Isotropic strains of the held-out paths [-] (p ~ 3e5 and ~ 4e6 N/m on the H-cell)."""
ORIENTATIONS_DEG = (0.0, 30.0, 90.0)
"""Cell orientations theta of the held-out legs [deg]."""
LATERAL_RATES = {2: {"constant-volume": -1.0, "drained": -0.5}, 3: {"constant-volume": -0.5, "drained": -0.25}}
"""Lateral macro strain rate b of each kind of leg per unit axial rate [-], by cell dimension."""
EPS_MAX = 0.15
"""Macro axial strain eps1 at the end of a leg [-]."""
RECORD_EVERY = 5e-3
"""Macro axial strain between two compared points [-]."""


@dataclass(frozen=True)
class Path:
    """One held-out path: ``kind`` (constant-volume or drained), ``theta_deg``, ``eps_iso``, leg direction (dim,)."""

    kind: str
    theta_deg: float
    eps_iso: float
    direction: np.ndarray


def held_out_paths(dim: int = 2) -> list[Path]:
    """The constant-volume and drained legs of cells of dimension ``dim`` at ``ORIENTATIONS_DEG``
    from every ``PRECOMPRESSION``."""
    paths = []
    for eps_iso in PRECOMPRESSION:
        for theta in ORIENTATIONS_DEG:
            c, s = math.cos(math.radians(theta)), math.sin(math.radians(theta))
            for kind, b in LATERAL_RATES[dim].items():
                paths.append(Path(kind, theta, eps_iso, np.array([c * c + b * s * s, s * s + b * c * c, b][:dim])))
    return paths


def _legs(paths: list[Path]) -> tuple[np.ndarray, int]:
    """Cell strain per unit macro strain eps1 of every leg (n_paths, dim), and the number of recorded points."""
    return np.stack([p.direction for p in paths]), int(round(EPS_MAX / RECORD_EVERY))


def _iso_steps(paths: list[Path], increment: float) -> np.ndarray:
    """Isotropic increments (n_steps, n_paths) of ``increment`` each, the last one shortened."""
    iso = np.array([p.eps_iso for p in paths])
    n = int(math.ceil(iso.max() / increment))
    done = np.minimum(np.arange(n + 1)[:, None] * increment, iso[None, :])
    return np.diff(done, axis=0)


def _run(step, paths: list[Path], increment: float) -> np.ndarray:
    """Diagonal moments (S_nn, S_tt or S_nn, S_t1t1, S_t2t2) [N m] at every recorded point,
    (n_points + 1, n_paths, dim), of a path stepped with ``increment``:
    ``step(d_eps (n_paths, dim)) -> moment (n_paths, dim, dim)``."""
    direction, n_points = _legs(paths)
    dim = direction.shape[1]
    for d in _iso_steps(paths, increment):
        moment = step(np.repeat(d[:, None], dim, axis=1))
    steps_per_point = max(1, int(round(RECORD_EVERY / increment)))
    diagonal = np.arange(dim)
    out = [moment[:, diagonal, diagonal]]
    for _ in range(n_points):
        for _ in range(steps_per_point):
            moment = step(direction * (RECORD_EVERY / steps_per_point))
        out.append(moment[:, diagonal, diagonal])
    return np.stack(out)


def dem_reference(meso: Mesostructure, law: ContactLaw, settings: DemSettings, paths: list[Path],
                  increment: float) -> np.ndarray:
    """DEM moments at the recorded points (as ``_run``), with the same increments as the ANN.

    Same increments matter: l <- l (1 - d_eps) compounds, so 1e-4 and 5e-3 steps reach cell
    sizes 4e-4 apart after 15 %, which is 2.5 % of a 1.5 % overlap.
    """
    dem = DemCell(law, float(meso.radius.mean()), settings=settings, threads=1)
    state = [dem.init_state(meso, len(paths))]

    def step(d_eps):
        state[0], response = dem.step(state[0], d_eps)
        return response.moment

    return _run(step, paths, increment)


def ann_rollout(net: MesoNet, reference_position: np.ndarray, reference_cell_size: np.ndarray, paths: list[Path],
                increment: float) -> np.ndarray:
    """ANN moments at the recorded points (as ``dem_reference``), recurrent from the touching cell."""
    n = len(paths)
    free = net.schema.free_dofs.numpy()
    state = [torch.tensor(np.tile(reference_cell_size, (n, 1)), dtype=torch.float64),
             torch.tensor(np.tile(reference_position[free[:, 0], free[:, 1]], (n, 1)), dtype=torch.float64),
             torch.zeros(n, *net.schema.shear_shape, dtype=torch.float64)]

    def step(d_eps):
        with torch.no_grad():
            new = net.advance(*state, torch.from_numpy(np.ascontiguousarray(d_eps, dtype=np.float64)))
        state[:] = [new.cell_size, new.free_position, new.shear_force]
        return new.moment.numpy()

    return _run(step, paths, increment)


def errors(ann: np.ndarray, dem: np.ndarray) -> np.ndarray:
    """Per path: ``max |S_ann - S_dem| / max |S_dem|`` over the path [-], shape (n_paths,)."""
    scale = np.abs(dem).max(axis=(0, 2))
    return np.abs(np.nan_to_num(ann, nan=np.inf) - dem).max(axis=(0, 2)) / np.where(scale > 0, scale, np.nan)


def rollout_report(net: MesoNet, meso: Mesostructure, law: ContactLaw, settings: DemSettings,
                   increments=(1e-4,)) -> dict:
    """Errors of every held-out path (cells of ``meso``'s dimension) at every increment, as a JSON-ready dict."""
    paths = held_out_paths(meso.dim)
    report = {"metric": "max over the path |S_ann - S_dem| (diagonal components) / max |S_dem| of the path",
              "eps_max": EPS_MAX, "paths": [{"kind": p.kind, "theta_deg": p.theta_deg, "eps_iso": p.eps_iso} for p in paths]}
    for increment in increments:
        dem = dem_reference(meso, law, settings, paths, increment)
        err = errors(ann_rollout(net, meso.position, meso.cell_size, paths, increment), dem)
        report[f"increment_{increment:g}"] = {"per_path": [float(e) for e in err], "max": float(np.max(err)),
                                              "median": float(np.median(err))}
    return report
