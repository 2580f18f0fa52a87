"""Run: yade -n -x tests/yade/cell3d_paths.py --cell CELL.json --path CASE.path.csv --out PREFIX

YADE reference of a 3D few-sphere cell (the ten-sphere H-cell or any mesostructure) along a
prescribed cell strain path. It is an independent check of the package's 3D DEM and closed
form, so it uses only YADE's own contact law and integrator:

- spheres of radius r_i; FrictMat with young_i = kn / r_i, so that Ip2_FrictMat_FrictMat_FrictPhys
  gives every pair the normal stiffness 2 E_i r_i E_j r_j / (E_i r_i + E_j r_j) = kn, and poisson =
  kt / kn (its ks = kn (nu_i + nu_j) / 2 = kt); Law2_ScGeom_FrictPhys_CundallStrack: linear normal
  spring without tension, incremental tangential spring rotated with the contact plane, Coulomb cap
  tan(phi_g) N, interaction erased (shear history reset) when it opens;
- or, where the settings' contact law has ``"law": "hertz-mindlin"`` (``shear_modulus`` G [Pa],
  ``poisson`` nu [-], ``phi_g_deg``): FrictMat with young = 2 G (1 + nu) and poisson = nu,
  Ip2_FrictMat_FrictMat_MindlinPhys (kno = 4/3 E* sqrt(R*), kso = 8 G* sqrt(R*)) and
  Law2_ScGeom_MindlinPhys_Mindlin (normal force kno uN^1.5, incremental shear spring of stiffness
  kso sqrt(uN), Coulomb cap, no damping or adhesion); the time step then uses the settings'
  ``dt_stiffness`` [N/m] in place of kn;
- Ig2_Sphere_Sphere_ScGeom with avoidGranularRatcheting=False, contacts detected up to a gap of
  ``contact_tolerance`` (r_i + r_j) (they carry no force until the spheres overlap);
- rotations blocked, no gravity, NewtonIntegrator with Cundall local damping,
  dt = dt_factor sqrt(m / kn) with m the mass of the smallest sphere (density 4/3 pi r^3); every
  sphere has the mass of the largest one times (r / r_max)^3.

Cell frame -> YADE axes: n = x, t1 = y, t2 = z. A DOF marked driven follows the cell strain
affinely (x_a = x_a,ref l_a / l_a,ref) through constant velocities over ceil(max|d_eps| /
strain_per_substep) substeps per path row; a free DOF is integrated. Then the cell relaxes
(driven DOFs at rest) until mean |F| over the free DOFs / mean |f| of the contacts carrying force
is below ``force_tolerance`` or ``max_substeps`` is spent (zero when nothing carries force).

Input:
- ``--cell``: JSON with ``radius`` (n_grains,) [m], ``position`` (n_grains, 3) [m] (n, t1, t2),
  ``driven`` (n_grains, 3) bool, ``cell_size`` (3,) [m] (written by ``make_reference3d.py``) and
  optionally ``mask`` (n_grains,) int: YADE's body masks, two grains interacting only where their masks
  share a bit (default 1 for every grain: all pairs);
- ``--path``: CSV with header ``d_eps_n,d_eps_t1,d_eps_t2``, one row per increment [-],
  compression positive (l_a <- l_a (1 - d_eps_a)).
The cell starts exactly as given (touching, force-free).

Output: ``PREFIX.yade.csv``, one row per path row (state after it): ``l1,l2,l3`` [m],
``S_nn,S_t1t1,S_t2t2,S_nt1,S_nt2,S_t1t2`` [N m] (Love-Weber moment over every contact, cell frame,
compression positive), ``x_n{i},x_t1{i},x_t2{i}`` [m] (grain centres, 1-based labels), and for every
pair i < j of the cell ``fn_{i}_{j}`` [N] (normal force, compression positive, 0 when open) and
``fs_{i}_{j}`` [N] (magnitude of the tangential force); ``PREFIX.json`` with every parameter, the
YADE version and run totals. Exit code 2 with a one-line message for bad input.
"""

from __future__ import annotations

import argparse
import csv
import inspect
import json
import math
import sys
import time
from itertools import combinations
from pathlib import Path

import numpy as np

REPO_ROOT = Path(inspect.currentframe().f_code.co_filename).resolve().parents[2]

import yade  # noqa: E402
from yade import O  # noqa: E402
from yade.wrapper import (  # noqa: E402
    Bo1_Sphere_Aabb,
    ForceResetter,
    FrictMat,
    Ig2_Sphere_Sphere_ScGeom,
    InsertionSortCollider,
    InteractionLoop,
    Ip2_FrictMat_FrictMat_FrictPhys,
    Ip2_FrictMat_FrictMat_MindlinPhys,
    Law2_ScGeom_FrictPhys_CundallStrack,
    Law2_ScGeom_MindlinPhys_Mindlin,
    NewtonIntegrator,
)
from yade.utils import sphere  # noqa: E402
from yade.minieigenHP import Vector3  # noqa: E402

AXES = "xyz"
"""YADE axis of each cell axis (n, t1, t2)."""
LABELS = ("n", "t1", "t2")


def read_path(path: Path) -> np.ndarray:
    """Strain path [-], shape (n_increments, 3), columns (d_eps_n, d_eps_t1, d_eps_t2), compression positive."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or [name.strip() for name in rows[0]] != ["d_eps_n", "d_eps_t1", "d_eps_t2"]:
        raise ValueError(f"{path}: header must be 'd_eps_n,d_eps_t1,d_eps_t2'")
    try:
        values = np.array([[float(v) for v in row] for row in rows[1:] if row], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if values.ndim != 2 or values.shape[1] != 3 or len(values) == 0:
        raise ValueError(f"{path}: expected one or more rows of three values")
    if not np.all(np.abs(values) < 1.0):
        raise ValueError(f"{path}: every |d_eps| must be < 1")
    return values


def read_cell(path: Path) -> dict:
    """The cell description (radius, position, driven, cell_size, mask) as numpy arrays."""
    data = json.loads(Path(path).read_text())
    cell = {"radius": np.asarray(data["radius"], dtype=np.float64),
            "position": np.asarray(data["position"], dtype=np.float64),
            "driven": np.asarray(data["driven"], dtype=bool),
            "cell_size": np.asarray(data["cell_size"], dtype=np.float64)}
    n = cell["radius"].size
    cell["mask"] = np.asarray(data.get("mask", [1] * n), dtype=np.int64)
    if cell["position"].shape != (n, 3) or cell["driven"].shape != (n, 3) or cell["cell_size"].shape != (3,):
        raise ValueError(f"{path}: expected position and driven of shape ({n}, 3) and cell_size of 3 values")
    if cell["mask"].shape != (n,) or np.any(cell["mask"] <= 0):
        raise ValueError(f"{path}: mask must hold {n} positive integers")
    return cell


class CellScene:
    """The YADE scene (global ``O``) holding one cell; ``ids[g]`` is the body id of grain g (0-based)."""

    def __init__(self, cell: dict, law: dict, settings: dict) -> None:
        self.cell = cell
        self.settings = settings
        radius = cell["radius"]
        r_max = float(radius.max())
        mass_max = settings["density"] * 4.0 / 3.0 * math.pi * r_max**3
        self.mass = mass_max * (radius / r_max) ** 3
        hertz = law.get("law", "linear") == "hertz-mindlin"
        stiffness = settings["dt_stiffness"] if hertz else law["kn"]
        self.dt = settings["dt_factor"] * math.sqrt(float(self.mass.min()) / stiffness)
        self.stretch = np.ones(3)
        O.reset()
        detection = 1.0 + settings["contact_tolerance"]
        O.engines = [
            ForceResetter(),
            InsertionSortCollider([Bo1_Sphere_Aabb(aabbEnlargeFactor=detection)]),
            InteractionLoop(
                [Ig2_Sphere_Sphere_ScGeom(interactionDetectionFactor=detection, avoidGranularRatcheting=False)],
                [Ip2_FrictMat_FrictMat_MindlinPhys() if hertz else Ip2_FrictMat_FrictMat_FrictPhys()],
                [Law2_ScGeom_MindlinPhys_Mindlin(neverErase=False) if hertz
                 else Law2_ScGeom_FrictPhys_CundallStrack(neverErase=False)],
            ),
            NewtonIntegrator(damping=settings["damping"], gravity=(0.0, 0.0, 0.0)),
        ]
        O.dt = self.dt
        ids = []
        for g, (r, x, driven) in enumerate(zip(radius, cell["position"], cell["driven"])):
            if hertz:
                young, poisson = 2.0 * law["shear_modulus"] * (1.0 + law["poisson"]), law["poisson"]
            else:
                young, poisson = law["kn"] / r, law["kt_over_kn"]
            material = O.materials.append(FrictMat(young=young, poisson=poisson,
                                                   frictionAngle=math.radians(law["phi_g_deg"]),
                                                   density=settings["density"]))
            body = sphere(tuple(float(v) for v in x), float(r), material=material, fixed=False)
            body.mask = int(cell["mask"][g])
            body.state.blockedDOFs = "".join(AXES[a] for a in range(3) if driven[a]) + "XYZ"
            body.state.mass = float(self.mass[g])
            inertia = 0.4 * float(self.mass[g]) * r**2
            body.state.inertia = Vector3(inertia, inertia, inertia)
            ids.append(O.bodies.append(body))
        self.ids = np.array(ids, dtype=np.int64)
        self.settled = self.positions()

    def drive(self, d_eps: np.ndarray) -> int:
        """Apply one path row through constant velocities of the driven DOFs; return the substeps spent."""
        ratio = float(np.max(np.abs(d_eps))) / self.settings["strain_per_substep"]
        n_sub = max(1, math.ceil(ratio * (1.0 - 1e-12)))
        self.stretch = self.stretch * (1.0 - np.asarray(d_eps, dtype=np.float64))
        target = self.cell["position"] * self.stretch
        duration = n_sub * self.dt
        driven = self.cell["driven"]
        for g, body_id in enumerate(self.ids):
            state = O.bodies[int(body_id)].state
            pos, vel = tuple(state.pos), tuple(state.vel)
            state.vel = Vector3(*((target[g, a] - pos[a]) / duration if driven[g, a] else vel[a] for a in range(3)))
        for _ in range(n_sub):
            O.step()
        for g, body_id in enumerate(self.ids):
            state = O.bodies[int(body_id)].state
            pos, vel = tuple(state.pos), tuple(state.vel)
            state.pos = Vector3(*(target[g, a] if driven[g, a] else pos[a] for a in range(3)))
            state.vel = Vector3(*(0.0 if driven[g, a] else vel[a] for a in range(3)))
        return n_sub

    def unbalanced(self) -> float:
        """Mean |F| over the free DOFs / mean |f| of the contacts carrying force [-]; 0 if none."""
        contact_sum, n_contacts = 0.0, 0
        for interaction in O.interactions:
            if interaction.isReal:
                magnitude = (interaction.phys.normalForce + interaction.phys.shearForce).norm()
                if magnitude > 0.0:
                    contact_sum += magnitude
                    n_contacts += 1
        if n_contacts == 0:
            return 0.0
        free = [abs(O.forces.f(int(body_id))[a]) for g, body_id in enumerate(self.ids)
                for a in range(3) if not self.cell["driven"][g, a]]
        return (sum(free) / max(len(free), 1)) / (contact_sum / n_contacts)

    def relax(self) -> tuple[int, float]:
        """Step with the driven DOFs at rest until quasi-static; return (substeps, final ratio)."""
        for n in range(1, self.settings["max_substeps"] + 1):
            before = self.positions()
            O.step()
            ratio = self.unbalanced()
            if ratio < self.settings["force_tolerance"]:
                break
        self.settled = before
        return n, ratio

    def positions(self) -> np.ndarray:
        """Grain centres [m], shape (n_grains, 3), columns (n, t1, t2)."""
        return np.array([tuple(O.bodies[int(i)].state.pos) for i in self.ids])

    def record(self) -> list[float]:
        """One output row for the state left by ``relax``."""
        pos = self.settled
        index = {int(body_id): g for g, body_id in enumerate(self.ids)}
        moment = np.zeros((3, 3))
        normal, shear = {}, {}
        for interaction in O.interactions:
            i1, i2 = int(interaction.id1), int(interaction.id2)
            if not interaction.isReal:
                continue
            force = np.array(tuple(interaction.phys.normalForce + interaction.phys.shearForce))  # on body id2
            g1, g2 = index[i1], index[i2]
            branch = pos[g2] - pos[g1]
            moment += np.outer(force, branch)
            key = (min(g1, g2), max(g1, g2))
            normal[key] = float(np.linalg.norm(tuple(interaction.phys.normalForce)))
            shear[key] = float(np.linalg.norm(tuple(interaction.phys.shearForce)))
        size = self.cell["cell_size"] * self.stretch
        n_grains = len(self.ids)
        pairs = list(combinations(range(n_grains), 2))
        return (list(size) + [moment[0, 0], moment[1, 1], moment[2, 2], moment[0, 1], moment[0, 2], moment[1, 2]]
                + [float(v) for v in pos.ravel()] + [normal.get(p, 0.0) for p in pairs]
                + [shear.get(p, 0.0) for p in pairs])


def header(n_grains: int) -> list[str]:
    """Columns of the output CSV."""
    pairs = list(combinations(range(1, n_grains + 1), 2))
    return (["l1", "l2", "l3", "S_nn", "S_t1t1", "S_t2t2", "S_nt1", "S_nt2", "S_t1t2"]
            + [f"x_{axis}{g}" for g in range(1, n_grains + 1) for axis in LABELS]
            + [f"fn_{i}_{j}" for i, j in pairs] + [f"fs_{i}_{j}" for i, j in pairs])


def parse_args(argv: list[str]) -> argparse.Namespace:
    """Command line of the script (arguments after the script name; a lone ``--`` is ignored)."""
    parser = argparse.ArgumentParser(prog="yade -n -x tests/yade/cell3d_paths.py",
                                     description="YADE 3D few-sphere cell along a cell strain path.",
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--cell", type=Path, required=True, help="cell JSON (radius, position, driven, cell_size)")
    parser.add_argument("--path", type=Path, required=True, help="CSV with header d_eps_n,d_eps_t1,d_eps_t2")
    parser.add_argument("--out", type=Path, required=True, help="output prefix: writes PREFIX.yade.csv, PREFIX.json")
    parser.add_argument("--settings", type=Path, required=True,
                        help="JSON of the contact law (kn, kt_over_kn, phi_g_deg) and the DEM settings")
    return parser.parse_args([a for a in argv if a != "--"])


def main(argv: list[str]) -> int:
    """Entry point; returns the exit code."""
    args = parse_args(argv)
    try:
        cell = read_cell(args.cell)
        path = read_path(args.path)
        config = json.loads(args.settings.read_text())
        law, settings = config["contact_law"], config["dem"]
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scene = CellScene(cell, law, settings)
    rows, drive_steps, relax_steps, worst, n_capped = [], 0, 0, 0.0, 0
    start = time.perf_counter()
    for d_eps in path:
        drive_steps += scene.drive(d_eps)
        steps, ratio = scene.relax()
        relax_steps += steps
        worst = max(worst, ratio)
        n_capped += ratio >= settings["force_tolerance"]
        rows.append(scene.record())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    columns = header(len(cell["radius"]))
    with open(f"{args.out}.yade.csv", "w", newline="") as handle:
        handle.write(",".join(columns) + "\n")
        for row in rows:
            handle.write(",".join(f"{v:.10e}" for v in row) + "\n")
    meta = {
        "description": "YADE 3D few-sphere cell along a prescribed cell strain path (tests/yade/cell3d_paths.py)",
        "yade_version": yade.config.version,
        "cell_file": args.cell.name,
        "path_file": args.path.name,
        "contact_law": law,
        "dem": settings,
        "dt_s": scene.dt,
        "frame": "cell n = YADE x, t1 = YADE y, t2 = YADE z",
        "sign_convention": "compression and contraction positive",
        "columns": columns,
        "units": "lengths m, forces N, S N m",
        "n_increments": len(path),
        "driving_substeps": drive_steps,
        "relaxation_substeps": relax_steps,
        "rows_relaxation_capped": int(n_capped),
        "max_final_unbalanced_ratio": worst,
        "wall_s": time.perf_counter() - start,
    }
    with open(f"{args.out}.json", "w") as handle:
        json.dump(meta, handle, indent=1)
        handle.write("\n")
    print(f"{args.out}.yade.csv: {len(rows)} rows, {meta['wall_s']:.1f} s, capped {n_capped}")
    return 0


if __name__ == "__main__":
    code = main(sys.argv[1:])
    if code:
        sys.exit(code)
