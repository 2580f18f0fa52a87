"""Run: yade -n -x tests/yade/hcell_paths.py --path CASE.path.csv --alpha0-deg 55 --out PREFIX

YADE reference of the six-disk H-cell (docs/model.md, sections 2-4 and 10) along a
prescribed cell strain path. It is an independent check of the analytical and Warp DEM
backends, so it uses only YADE's own contact law and integrator:

- spheres of radius r in the plane z = 0, FrictMat + Ip2_FrictMat_FrictMat_FrictPhys +
  Law2_ScGeom_FrictPhys_CundallStrack: linear normal spring without tension (kn = young r
  for equal spheres, so young = kn / r), incremental tangential spring ks = poisson kn with
  a Coulomb cap tan(phi_g) N, interaction erased (shear history reset) when it opens;
- Ig2_Sphere_Sphere_ScGeom with avoidGranularRatcheting=False, contacts detected up to a
  gap of ``contact_tolerance`` D (they carry no force until the disks overlap);
- rotations blocked, no gravity, NewtonIntegrator with Cundall local damping,
  dt = dt_factor sqrt(m / kn) with the disk mass m = density pi r^2.

The law and the numerical settings are written out below (``Law``, ``Settings``, ``RADIUS``):
the script imports nothing from the package it checks.

Cell frame -> YADE axes: n (cell axis) = YADE x, t (lateral) = YADE y. Grains 1 and 4 are
driven along n and t, grains 2, 3, 5, 6 along t and free along n (spec section 3). A driven
coordinate follows the cell strain affinely (x_n = x_n_ref l1 / l1_ref,
x_t = x_t_ref l2 / l2_ref) through constant velocities over ceil(max|d_eps| /
strain_per_substep) substeps per path row, then the cell relaxes (driven grains at rest)
until the unbalanced force ratio of the FREE degrees of freedom is below
``force_tolerance`` or ``max_substeps`` is spent. YADE's own ``unbalancedForce()`` cannot
be used for this: it counts the full force on grains 2, 3, 5, 6, including the t
component carried by the driver (F2), which never vanishes. The ratio used here is
mean_{grains 2,3,5,6} |F_n| / mean_{contacts with force} |f|, zero when no contact carries
force (stress-free mechanism).

Input: ``--path``: CSV with header ``d_eps_n,d_eps_t``, one row per increment [-],
compression positive (l1 <- l1 (1 - d_eps_n), l2 <- l2 (1 - d_eps_t)); ``--alpha0-deg``:
initial opening angle [deg]. The cell starts exactly touching with zero forces.

Output: ``PREFIX.yade.csv``, one row per path row (state after it), columns
``l1,l2`` [m], ``alpha_deg`` [deg], ``d1,d2`` [m] (mean branch lengths of the type-1 and
type-2 pairs), ``N1,N2`` [N] (mean normal forces of type-1 / type-2 contacts, compression
positive, 0 when open), ``T1`` [N] (mean tangential force of type-1 contacts, T1 > 0
resists opening, spec section 4), ``S_nn,S_tt`` [N m] (Love-Weber moment over every
contact of the cell, pathological 1-4, 2-6, 3-5 included, cell frame, compression
positive), ``x_n1,x_t1,...,x_n6,x_t6`` [m] (grain centres in the cell frame, cell centre
at the origin); and ``PREFIX.json`` with every parameter, the YADE version and run totals.
``l1, l2`` are the imposed lengths; the positions are those the recorded forces were
computed from (before the last relaxation substep). Where every contact is open the cell
is a stress-free mechanism: its free grains keep, undamped, the velocity they had when the
last contact opened, so their n coordinates there are not fixed by statics. With
``--rest-unloaded`` a free grain that the last step left without force is stopped instead (its
n velocity set to zero before each step), as the closed form keeps y2 (docs/model.md, section
6): a path that closes contacts again after opening them all then starts the new contacts from
a defined state.
Exit code 2 with a one-line message for bad input.

Also imported (inside YADE) by benchmarks/bench_yade.py, which builds many cells with
``HCellScene``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import yade
from yade import O
from yade.wrapper import (
    Bo1_Sphere_Aabb,
    ForceResetter,
    FrictMat,
    Ig2_Sphere_Sphere_ScGeom,
    InsertionSortCollider,
    InteractionLoop,
    Ip2_FrictMat_FrictMat_FrictPhys,
    Law2_ScGeom_FrictPhys_CundallStrack,
    NewtonIntegrator,
)
from yade.utils import sphere
from yade.minieigenHP import Vector3

N_GRAINS = 6
TYPE1_PAIRS = ((1, 2), (1, 6), (4, 3), (4, 5))
"""Type-1 contacts as (outer grain, lateral grain) labels."""
TYPE2_PAIRS = ((2, 3), (6, 5))
"""Type-2 contacts as (upper, lower) lateral grain labels."""
FREE_LABELS = (2, 3, 5, 6)
"""Grains whose n coordinate is free."""
HEADER = ("l1", "l2", "alpha_deg", "d1", "d2", "N1", "N2", "T1", "S_nn", "S_tt") + tuple(
    f"x_{axis}{label}" for label in range(1, N_GRAINS + 1) for axis in ("n", "t")
)
"""Columns of the output CSV."""


ALPHA0_RANGE_DEG = (30.0, 90.0)
"""Opening angles [deg] the cell exists for (lateral grains 2-6 meet at 30, axial grains 1-4 at 90)."""


@dataclass(frozen=True)
class Law:
    """The contact law of the reference cases (docs/model.md, section 1), written out here so that
    the reference does not depend on the package it checks."""

    kn: float = 2e8
    """Normal stiffness [N/m]."""
    kt_over_kn: float = 0.5
    """Tangential over normal stiffness [-]."""
    phi_g_deg: float = 30.0
    """Inter-granular friction angle [deg]."""


@dataclass(frozen=True)
class Settings:
    """Numerical settings of the reference runs (those every committed case was run with)."""

    density: float = 2650.0
    """Grain density [kg/m^3]."""
    dt_factor: float = 0.2
    """Time step over sqrt(m / kn) [-]."""
    damping: float = 0.5
    """Cundall local damping [-]."""
    strain_per_substep: float = 2.5e-7
    """Largest cell-strain component per driving substep [-]."""
    force_tolerance: float = 1e-6
    """Free-DOF unbalanced force ratio that ends a relaxation [-]."""
    max_substeps: int = 200_000
    """Relaxation substeps allowed per row [-]."""
    contact_tolerance: float = 1e-9
    """Gap, as a fraction of D, up to which a pair is detected as a contact [-]."""


RADIUS = 0.5
"""Grain radius r [m] (docs/model.md, section 1)."""
DEFAULT_ALPHA0_DEG = 55.0
"""Default initial opening angle [deg]."""


def check_alpha0_deg(alpha0_deg: float) -> float:
    """``alpha0_deg`` as float if within ``ALPHA0_RANGE_DEG`` (upper end excluded); ValueError otherwise."""
    value = float(alpha0_deg)
    low, high = ALPHA0_RANGE_DEG
    if not (low <= value < high):
        raise ValueError(f"alpha0 = {value:g} deg is outside [{low:g}, {high:g}) deg")
    return value


def reference_positions(alpha0: float, radius: float) -> np.ndarray:
    """Touching H-cell of spec section 2 (d1 = d2 = D).

    Args:
        alpha0: initial opening angle [rad].
        radius: grain radius r [m].

    Returns:
        Grain centres [m], shape (6, 2), columns (x_n, x_t), row = label - 1, cell centre
        at the origin.
    """
    diameter = 2.0 * radius
    c, s = math.cos(alpha0), math.sin(alpha0)
    return np.array(
        [
            [0.5 * diameter + diameter * c, 0.0],
            [0.5 * diameter, -diameter * s],
            [-0.5 * diameter, -diameter * s],
            [-0.5 * diameter - diameter * c, 0.0],
            [-0.5 * diameter, diameter * s],
            [0.5 * diameter, diameter * s],
        ]
    )


def read_path(path: Path) -> np.ndarray:
    """Strain path [-], shape (n_increments, 2), columns (d_eps_n, d_eps_t), compression positive.

    Raises:
        ValueError: (one line) on a wrong header, a non-numeric value or |d_eps| >= 1.
    """
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or [name.strip() for name in rows[0]] != ["d_eps_n", "d_eps_t"]:
        raise ValueError(f"{path}: header must be 'd_eps_n,d_eps_t'")
    try:
        values = np.array([[float(v) for v in row] for row in rows[1:] if row], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if values.ndim != 2 or values.shape[1] != 2 or len(values) == 0:
        raise ValueError(f"{path}: expected one or more rows of two values")
    if not np.all(np.abs(values) < 1.0):
        raise ValueError(f"{path}: every |d_eps| must be < 1")
    return values


class HCellScene:
    """The YADE scene (global ``O``) holding ``n_cells`` identical, independent H-cells.

    Cells sit side by side along the t axis (YADE y), ``spacing`` apart, all following the
    same cell strain. ``ids[k, label - 1]`` is the YADE body id of grain ``label`` of cell
    ``k``; ``origin[k]`` its centre (n, t) [m]; ``stretch`` the current (l1 / l1_ref,
    l2 / l2_ref) [-].
    """

    def __init__(
        self,
        alpha0_deg: float,
        n_cells: int,
        law: Law,
        radius: float,
        settings: Settings,
        rest_unloaded: bool = False,
    ) -> None:
        self.rest_unloaded = rest_unloaded
        self.law = law
        self.radius = radius
        self.settings = settings
        self.alpha0 = math.radians(check_alpha0_deg(alpha0_deg))
        self.reference = reference_positions(self.alpha0, radius)
        self.mass = settings.density * math.pi * radius**2
        self.dt = settings.dt_factor * math.sqrt(self.mass / law.kn)
        self.stretch = np.ones(2)
        spacing = 2.0 * float(np.max(np.abs(self.reference[:, 1]))) + 4.0 * radius
        self.origin = np.zeros((n_cells, 2))
        self.origin[:, 1] = spacing * np.arange(n_cells)

        O.reset()
        material = O.materials.append(
            FrictMat(
                young=law.kn / radius,
                poisson=law.kt_over_kn,
                frictionAngle=math.radians(law.phi_g_deg),
                density=settings.density,
            )
        )
        detection = 1.0 + settings.contact_tolerance
        O.engines = [
            ForceResetter(),
            InsertionSortCollider([Bo1_Sphere_Aabb(aabbEnlargeFactor=detection)]),
            InteractionLoop(
                [Ig2_Sphere_Sphere_ScGeom(interactionDetectionFactor=detection, avoidGranularRatcheting=False)],
                [Ip2_FrictMat_FrictMat_FrictPhys()],
                [Law2_ScGeom_FrictPhys_CundallStrack(neverErase=False)],
            ),
            NewtonIntegrator(damping=settings.damping, gravity=(0.0, 0.0, 0.0)),
        ]
        O.dt = self.dt
        inertia = 0.5 * self.mass * radius**2
        ids = []
        for origin in self.origin:
            cell = []
            for label in range(1, N_GRAINS + 1):
                x_n, x_t = origin + self.reference[label - 1]
                body = sphere((x_n, x_t, 0.0), radius, material=material, fixed=False)
                body.state.blockedDOFs = "yzXYZ" if label in FREE_LABELS else "xyzXYZ"
                body.state.mass = self.mass
                body.state.inertia = Vector3(inertia, inertia, inertia)
                cell.append(O.bodies.append(body))
            ids.append(cell)
        self.ids = np.array(ids, dtype=np.int64)
        self._driven_n = self.ids[:, [0, 3]].ravel()
        self._free = self.ids[:, [label - 1 for label in FREE_LABELS]].ravel()
        self.settled = self.positions()

    def _targets(self) -> np.ndarray:
        """Driven-coordinate targets [m] of every grain at the current stretch, shape (n_cells, 6, 2)."""
        return self.origin[:, None, :] + self.reference[None, :, :] * self.stretch[None, None, :]

    def start_row(self, d_eps: np.ndarray) -> int:
        """Set the driving velocities of one path row (d_eps_n, d_eps_t) [-]; return its substeps.

        The driven coordinates will reach their targets at constant velocity after
        ceil(max|d_eps| / strain_per_substep) substeps; free components keep their velocity.
        """
        # The relative slack keeps exact multiples (2e-4 / 2.5e-7) from rounding up a substep.
        ratio = float(np.max(np.abs(d_eps))) / self.settings.strain_per_substep
        n_sub = max(1, math.ceil(ratio * (1.0 - 1e-12)))
        self.stretch = self.stretch * (1.0 - np.asarray(d_eps, dtype=np.float64))
        self._row_targets = self._targets()
        duration = n_sub * self.dt
        bodies = O.bodies
        for k, cell in enumerate(self.ids):
            for index, body_id in enumerate(cell):
                state = bodies[int(body_id)].state
                pos = state.pos
                target = self._row_targets[k, index]
                v_t = (target[1] - pos[1]) / duration
                v_n = (target[0] - pos[0]) / duration if index in (0, 3) else state.vel[0]
                state.vel = Vector3(v_n, v_t, 0.0)
        return n_sub

    def finish_row(self) -> None:
        """Set the driven coordinates exactly on their targets (a rounding-level correction) and stop them."""
        bodies = O.bodies
        for k, cell in enumerate(self.ids):
            for index, body_id in enumerate(cell):
                state = bodies[int(body_id)].state
                driven_n = index in (0, 3)
                target = self._row_targets[k, index]
                x_n = target[0] if driven_n else state.pos[0]
                state.pos = Vector3(x_n, target[1], 0.0)
                state.vel = Vector3(0.0 if driven_n else state.vel[0], 0.0, 0.0)

    def drive(self, d_eps: np.ndarray) -> int:
        """Apply one path row (d_eps_n, d_eps_t) [-] through velocities; return the substeps spent."""
        n_sub = self.start_row(d_eps)
        for _ in range(n_sub):
            self.stop_unloaded()
            O.step()
        self.finish_row()
        return n_sub

    def stop_unloaded(self) -> None:
        """With ``rest_unloaded``: set the n velocity of every free grain that the last step left
        without force to zero (a grain nothing pushes has no quasi-static reason to move)."""
        if not self.rest_unloaded:
            return
        bodies = O.bodies
        for body_id in self._free:
            force = O.forces.f(int(body_id))
            if force[0] == 0.0 and force[1] == 0.0:
                state = bodies[int(body_id)].state
                state.vel = Vector3(0.0, state.vel[1], 0.0)

    def unbalanced(self) -> float:
        """Mean |F_n| on the free grains / mean |f| of the contacts carrying force [-]; 0 if none."""
        contact_sum, n_contacts = 0.0, 0
        for interaction in O.interactions:
            if not interaction.isReal:
                continue
            magnitude = (interaction.phys.normalForce + interaction.phys.shearForce).norm()
            if magnitude > 0.0:
                contact_sum += magnitude
                n_contacts += 1
        if n_contacts == 0:
            return 0.0
        free_sum = sum(abs(O.forces.f(int(body_id))[0]) for body_id in self._free)
        return (free_sum / len(self._free)) / (contact_sum / n_contacts)

    def relax(self) -> tuple[int, float]:
        """Step with the driven grains at rest until quasi-static; return (substeps, final ratio).

        At least one substep is taken, so forces always match the final driven positions.
        ``settled`` keeps the grain centres the final forces were computed from (the
        positions before the last substep), like a DEM that tests equilibrium before moving.
        """
        for n in range(1, self.settings.max_substeps + 1):
            before = self.positions()
            self.stop_unloaded()
            O.step()
            ratio = self.unbalanced()
            if ratio < self.settings.force_tolerance:
                break
        self.settled = before
        return n, ratio

    def contact_stiffness(self) -> dict[str, float] | None:
        """kn [N/m], ks [N/m] and tan(phi_g) [-] that YADE computed for a closed contact; None if none."""
        for interaction in O.interactions:
            if interaction.isReal:
                phys = interaction.phys
                return {"kn": phys.kn, "ks": phys.ks, "tan_phi": phys.tangensOfFrictionAngle}
        return None

    def positions(self) -> np.ndarray:
        """Grain centres relative to their cell's origin [m], shape (n_cells, 6, 2), columns (x_n, x_t)."""
        bodies = O.bodies
        pos = np.array([[tuple(bodies[int(i)].state.pos)[:2] for i in cell] for cell in self.ids])
        return pos - self.origin[:, None, :]

    def contact_force(self, cell: int, label_a: int, label_b: int) -> np.ndarray:
        """Force of grain ``label_a`` on grain ``label_b`` [N], shape (2,), (n, t); zero if no contact."""
        id_a, id_b = int(self.ids[cell, label_a - 1]), int(self.ids[cell, label_b - 1])
        interaction = O.interactions[id_a, id_b] if O.interactions.has(id_a, id_b) else None
        if interaction is None or not interaction.isReal:
            return np.zeros(2)
        force = interaction.phys.normalForce + interaction.phys.shearForce  # on body id2
        on_b = np.array([force[0], force[1]])
        return on_b if interaction.id2 == id_b else -on_b

    def record(self, cell: int) -> list[float]:
        """Values of the ``HEADER`` columns for ``cell`` in the state left by ``relax``.

        Positions are ``settled`` (those the recorded contact forces were computed from).
        """
        pos = self.settled[cell]
        lengths, angles, normal, tangential = [], [], [], []
        for outer, lateral in TYPE1_PAIRS:
            branch = pos[lateral - 1] - pos[outer - 1]
            length = float(np.hypot(*branch))
            u = branch / length
            lateral_dir = np.array([0.0, math.copysign(1.0, u[1])])
            t_open = lateral_dir - (lateral_dir @ u) * u
            t_open /= np.hypot(*t_open)
            force = self.contact_force(cell, outer, lateral)
            lengths.append(length)
            angles.append(math.atan2(abs(branch[1]), abs(branch[0])))
            normal.append(float(force @ u))
            tangential.append(-float(force @ t_open))
        d2_values, n2_values = [], []
        for upper, lower in TYPE2_PAIRS:
            branch = pos[lower - 1] - pos[upper - 1]
            length = float(np.hypot(*branch))
            d2_values.append(length)
            n2_values.append(float(self.contact_force(cell, upper, lower) @ (branch / length)))
        index = {int(body_id): label_index for label_index, body_id in enumerate(self.ids[cell])}
        moment = np.zeros((2, 2))
        for interaction in O.interactions:
            i1, i2 = int(interaction.id1), int(interaction.id2)
            if not interaction.isReal or i1 not in index or i2 not in index:
                continue
            force = interaction.phys.normalForce + interaction.phys.shearForce  # on body id2
            moment += np.outer([force[0], force[1]], pos[index[i2]] - pos[index[i1]])
        l1 = (self.reference[0, 0] - self.reference[3, 0]) * self.stretch[0]
        l2 = (self.reference[5, 1] - self.reference[1, 1]) * self.stretch[1]
        return [
            l1,
            l2,
            math.degrees(float(np.mean(angles))),
            float(np.mean(lengths)),
            float(np.mean(d2_values)),
            float(np.mean(normal)),
            float(np.mean(n2_values)),
            float(np.mean(tangential)),
            moment[0, 0],
            moment[1, 1],
        ] + [float(v) for v in pos.ravel()]


def run_path(path: np.ndarray, alpha0_deg: float, law: Law, radius: float, settings: Settings,
             rest_unloaded: bool = False):
    """Run one cell along ``path`` (n_increments, 2); return (rows, totals dict)."""
    scene = HCellScene(alpha0_deg, 1, law, radius, settings, rest_unloaded)
    rows, drive_steps, relax_steps, worst, n_capped = [], 0, 0, 0.0, 0
    stiffness = None
    start = time.perf_counter()
    for d_eps in path:
        drive_steps += scene.drive(d_eps)
        steps, ratio = scene.relax()
        stiffness = stiffness or scene.contact_stiffness()
        relax_steps += steps
        worst = max(worst, ratio)
        n_capped += ratio >= settings.force_tolerance
        rows.append(scene.record(0))
    totals = {
        "n_increments": len(path),
        "driving_substeps": drive_steps,
        "relaxation_substeps": relax_steps,
        "rows_relaxation_capped": int(n_capped),
        "max_final_unbalanced_ratio": worst,
        "wall_s": time.perf_counter() - start,
        "yade_contact_stiffness": stiffness,
        "dt_s": scene.dt,
        "disk_mass_kg": scene.mass,
    }
    return rows, totals


def parse_args(argv: list[str]) -> argparse.Namespace:
    """Command line of the script (arguments after the script name; a lone ``--`` is ignored)."""
    settings = Settings()
    parser = argparse.ArgumentParser(
        prog="yade -n -x tests/yade/hcell_paths.py",
        description="YADE six-disk H-cell along a cell strain path (reference cases).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--path", type=Path, required=True, help="CSV with header d_eps_n,d_eps_t")
    parser.add_argument("--alpha0-deg", type=float, default=DEFAULT_ALPHA0_DEG, help="initial opening angle [deg]")
    parser.add_argument("--out", type=Path, required=True, help="output prefix: writes PREFIX.yade.csv, PREFIX.json")
    parser.add_argument(
        "--strain-per-substep",
        type=float,
        default=settings.strain_per_substep,
        help="largest cell-strain component per substep [-]",
    )
    parser.add_argument(
        "--force-tolerance", type=float, default=settings.force_tolerance, help="free-DOF unbalanced force ratio [-]"
    )
    parser.add_argument(
        "--rest-unloaded",
        action="store_true",
        help="hold free grains without force at rest (n velocity zero) instead of letting them coast",
    )
    return parser.parse_args([a for a in argv if a != "--"])


def main(argv: list[str]) -> int:
    """Entry point; returns the exit code."""
    args = parse_args(argv)
    law = Law()
    radius = RADIUS
    try:
        check_alpha0_deg(args.alpha0_deg)
        for name in ("strain_per_substep", "force_tolerance"):
            value = getattr(args, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"--{name.replace('_', '-')} = {value:g} must be finite and > 0")
        settings = Settings(strain_per_substep=args.strain_per_substep, force_tolerance=args.force_tolerance)
        path = read_path(args.path)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows, totals = run_path(path, args.alpha0_deg, law, radius, settings, args.rest_unloaded)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(f"{args.out}.yade.csv", "w", newline="") as handle:
        handle.write(",".join(HEADER) + "\n")
        for row in rows:
            handle.write(",".join(f"{v:.10e}" for v in row) + "\n")
    meta = {
        "description": "YADE six-disk H-cell along a prescribed cell strain path (tests/yade/hcell_paths.py)",
        "yade_version": yade.config.version,
        "path_file": args.path.name,
        "alpha0_deg": args.alpha0_deg,
        "radius_m": radius,
        "kn_N_per_m": law.kn,
        "kt_over_kn": law.kt_over_kn,
        "phi_g_deg": law.phi_g_deg,
        "yade_young_Pa": law.kn / radius,
        "yade_poisson": law.kt_over_kn,
        "density_kg_per_m3": settings.density,
        "dt_factor": settings.dt_factor,
        "damping": settings.damping,
        "strain_per_substep": settings.strain_per_substep,
        "force_tolerance": settings.force_tolerance,
        "max_substeps_per_relaxation": settings.max_substeps,
        "contact_tolerance": settings.contact_tolerance,
        **({"free_grains_without_force": "held at rest (--rest-unloaded)"} if args.rest_unloaded else {}),
        "frame": "cell n = YADE x, cell t = YADE y; outputs in (n, t), cell centre at the origin",
        "sign_convention": "compression and contraction positive; T1 > 0 resists opening",
        "unbalanced_ratio": "mean |F_n| on grains 2,3,5,6 / mean |f| of contacts carrying force",
        "columns": list(HEADER),
        "units": "lengths m, angles deg, forces N, S N m",
        **totals,
    }
    with open(f"{args.out}.json", "w") as handle:
        json.dump(meta, handle, indent=1)
        handle.write("\n")
    print(f"{args.out}.yade.csv: {len(rows)} rows, {totals['wall_s']:.1f} s, capped {totals['rows_relaxation_capped']}")
    return 0


if __name__ == "__main__":
    code = main(sys.argv[1:])
    if code:
        sys.exit(code)
