"""The meso-ANN's compiled increments re-run in processes compiled for other CPUs, emulated on this one.

``python tests/other_cpus.py DIR CHECK...`` (the environment names the CPU, ``OTHER_CPUS``): for each check,
reads ``DIR/CHECK.in.npz`` (``cell_size``, ``free_position``, ``shear_force``, ``d_eps``, and ``index``, a
sub-batch evaluated on its own) and writes ``DIR/CHECK.out.npz``: every field of the check's increment
(``fields``) for the whole batch (``whole_*``) and for the sub-batch (``part_*``).

One process per CPU computes every check, so that numba compiles each CPU's kernels once (cold in a fresh
clone; its cache is keyed by CPU name); ``run_other_cpus`` starts the CPUs' processes at once. The checks'
states are built here (``planar_loaded``, ``spatial_loaded``, ``sheared``), once per test process, and the
inference tests' module fixtures take the same ones.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LARGE_AXIAL = ROOT / "benchmarks" / "cells" / "large_axial.toml"
HARD_CASES = ROOT / "tests" / "data" / "equilibrium" / "large_axial_hard.npz"
"""Cell-increments of ``benchmarks/cells/large_axial.toml`` where full Newton steps fail (README beside it)."""
OTHER_CPUS = {
    "SSE2 vectors, software FMA, other BLAS kernels": {"NUMBA_CPU_NAME": "generic", "OPENBLAS_CORETYPE": "Nehalem"},
    "AVX2 vectors, FMA hardware": {"NUMBA_CPU_NAME": "haswell", "OPENBLAS_CORETYPE": "Haswell"},
}
"""Compiler settings (and BLAS kernels) of another CPU, emulated on this one: no increment may change a bit. The
two ends of x86-64 below the AVX-512 host: no vectors wider than SSE2 and no FMA, and the AVX2 and FMA of most
CI machines (``make determinism``'s AVX2 and lowest settings then load these CPUs' kernels from numba's cache)."""
COMPILED_SIGNAL = "OTHER_CPUS_COMPILED"
"""Environment variable naming a file that ``run_other_cpus``'s caller creates once the other CPUs' processes have
finished (``make determinism``'s settings for those CPUs then start: numba's cache holds their kernels)."""


def relaxing_network(spec: str = str(LARGE_AXIAL)):
    """A network (``MesoNet``) of the cell ``spec`` whose output layer is zero: its first guess is the relaxation
    along the unbalanced force alone, the same in torch and compiled (no weight enters it)."""
    import torch  # noqa: PLC0415 (the worker of the planar check alone needs no spatial network)

    from training.cell_physics import CellSchema  # noqa: PLC0415
    from training.network import MesoNet  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415
    from warp_hcell.mesostructures.builders import mesostructure_arg  # noqa: PLC0415

    meso, law = mesostructure_arg(spec).build(None), ContactLaw()
    schema = CellSchema.from_arrays(radius=meso.radius, reference_position=meso.position,
                                    reference_cell_size=meso.cell_size, driven=meso.driven, pairs=meso.pairs,
                                    outer=meso.outer, kn=law.kn, kt=law.kt, mu=law.mu,
                                    contact_tolerance=meso.contact_tolerance)
    net = MesoNet(schema, torch.ones(schema.n_pairs, dtype=torch.bool), hidden=(16,))
    with torch.no_grad():
        net.mlp[-1].weight.zero_()
        net.mlp[-1].bias.zero_()
    return net


def _shipped(dim: int, corrections: int = 0, tolerance: float | None = None):
    from homogenization.ann.cell import AnnCell, AnnCell3D  # noqa: PLC0415
    from training.inference import FastAdvance  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415

    return FastAdvance((AnnCell if dim == 2 else AnnCell3D)(ContactLaw(), 0.5).net, corrections, tolerance)


def _globalised():
    from training.inference import FastAdvance  # noqa: PLC0415

    return FastAdvance(relaxing_network(), 20)  # the DEM's tolerance


@dataclass(frozen=True)
class Check:
    """One compiled increment checked on other CPUs: ``build`` makes its ``FastAdvance``; ``tangent``: its
    tangent is a field too; ``shipped_3d``: it needs the shipped 3D model."""

    build: Callable
    tangent: bool = False
    shipped_3d: bool = False


CHECKS = {
    "planar": Check(lambda: _shipped(2), tangent=True),
    "spatial": Check(lambda: _shipped(3), shipped_3d=True),
    "corrected": Check(lambda: _shipped(3, 2, 1e-6), shipped_3d=True),
    "globalised": Check(_globalised),
}
"""The shipped planar model with its tangent; the shipped spatial model, alone and with 2 equilibrium corrections;
``relaxing_network`` with 20 corrections (halved and shifted Newton steps fire on ``HARD_CASES``)."""


def fields(fast, state: tuple[np.ndarray, ...], d_eps: np.ndarray, tangent: bool) -> dict[str, np.ndarray]:
    """Every field of ``fast``'s increment of ``state`` by ``d_eps``, its tangent with ``tangent``, and the counts of
    its corrections where it takes any."""
    increment, jacobian = fast.increment(*state, d_eps, with_tangent=tangent)
    out = {name: np.asarray(value) for name, value in increment._asdict().items()}
    if tangent:
        out["tangent"] = jacobian
    corrections = fast.last_corrections()
    return out if corrections is None else {**out, **{k: np.asarray(v) for k, v in corrections._asdict().items()}}


def sub_batch(name: str, value: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The cells ``index`` of the field ``name`` of a whole batch (``force_ratio`` has its cells last)."""
    return value[..., index] if name == "force_ratio" else value[index]


def evaluate(check: str, data) -> dict[str, np.ndarray]:
    """``whole_*`` and ``part_*`` fields (``fields``) of ``check`` on the inputs ``data`` (module docstring)."""
    fast = CHECKS[check].build()
    state = tuple(np.asarray(data[name]) for name in ("cell_size", "free_position", "shear_force"))
    d_eps, index = np.asarray(data["d_eps"]), np.asarray(data["index"])
    tangent = CHECKS[check].tangent
    whole = fields(fast, state, d_eps, tangent)
    part = fields(fast, tuple(a[index] for a in state), d_eps[index], tangent)
    return {**{f"whole_{k}": v for k, v in whole.items()}, **{f"part_{k}": v for k, v in part.items()}}


@functools.cache
def planar_loaded():
    """(cell, state, probes): 40 planar cells of the shipped model compressed, then sheared until contacts slide;
    the probes include a zero one and one below the relaxation ramp."""
    from homogenization.ann.cell import AnnCell  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415
    from warp_hcell.mesostructures.hcell import h_cell  # noqa: PLC0415

    cell = AnnCell(ContactLaw(), 0.5)
    rng = np.random.default_rng(1)
    n = 40
    state = cell.init_state([h_cell(a) for a in rng.uniform(35.0, 65.0, n)], n)
    shear = np.stack([np.ones(n), -np.ones(n)], axis=1) * rng.choice([-1.0, 1.0], size=(n, 1))
    for k in range(80):
        state, _ = cell.step(state, np.full((n, 2), 4e-4) if k < 30 else 2e-4 * shear)
    d = 1e-4 * shear + rng.normal(scale=2e-5, size=(n, 2))
    d[0] = 0.0
    d[1] = [3e-8, 0.0]
    return cell, state, d


@functools.cache
def spatial_loaded():
    """(cell, state, probes): 40 spatial cells compressed isotropically, then sheared at random deviatoric rates
    until contacts slide; the probes include a zero one and one below the relaxation ramp."""
    from homogenization.ann.cell import AnnCell3D  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415
    from warp_hcell.mesostructures.builders import mesostructure_arg  # noqa: PLC0415

    cell = AnnCell3D(ContactLaw(), 0.5)
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    rng = np.random.default_rng(1)
    n = 40
    state = cell.init_state(meso, n)
    shear = np.array([1.0, -0.5, -0.5]) * rng.choice([-1.0, 1.0], size=(n, 1)) + rng.normal(scale=0.3, size=(n, 3))
    for k in range(150):
        state, _ = cell.step(state, np.full((n, 3), 3e-4) if k < 30 else 2e-4 * shear)
    d = 1e-4 * shear + rng.normal(scale=2e-5, size=(n, 3))
    d[0] = 0.0
    d[1] = [3e-8, 0.0, 0.0]
    return cell, state, d


@functools.cache
def sheared():
    """(cell, mesostructure, state, probe): 30 spatial cells of the shipped model, compressed isotropically then
    sheared at random deviatoric rates (contacts slide), and one undrained probe."""
    from homogenization.ann.cell import AnnCell3D  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415
    from warp_hcell.mesostructures.builders import mesostructure_arg  # noqa: PLC0415

    cell = AnnCell3D(ContactLaw(), 0.5)
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    rng = np.random.default_rng(0)
    n = 30
    state = cell.init_state(meso, n)
    for k in range(300):
        d = (np.full((n, 3), 1e-4) if k < 100 else
             np.column_stack([np.full(n, 1e-4), -0.5e-4 + 3e-5 * rng.standard_normal(n),
                              -0.5e-4 + 3e-5 * rng.standard_normal(n)]))
        state, _ = cell.step(state, d)
    return cell, meso, state, np.tile([1e-4, -0.5e-4, -0.5e-4], (n, 1))


def sheared_probe(d_eps: np.ndarray) -> np.ndarray:
    """``sheared``'s probe scaled by a random factor per cell (corrections of different lengths)."""
    return d_eps * (1.0 + 0.3 * np.random.default_rng(2).standard_normal((d_eps.shape[0], 1)))


def _state_inputs(state, d_eps: np.ndarray, index: list[int]) -> dict[str, np.ndarray]:
    return {"cell_size": np.asarray(state.cell_size), "free_position": np.asarray(state.free_position),
            "shear_force": np.asarray(state.shear_force), "d_eps": d_eps, "index": np.array(index)}


def inputs(check: str) -> dict[str, np.ndarray]:
    """The inputs of ``check`` (module docstring): the tests' states and probes, and a sub-batch with a repeated cell."""
    if check == "planar":
        _, state, d = planar_loaded()
        return _state_inputs(state, d, [5, 0, 39, 5, 17])
    if check == "spatial":
        _, state, d = spatial_loaded()
        return _state_inputs(state, d, [5, 0, 39, 5, 17])
    if check == "corrected":
        _, _, state, d_eps = sheared()
        return _state_inputs(state, sheared_probe(d_eps), [5, 0, 29, 5, 17])
    data = np.load(HARD_CASES)
    return {**{name: data[name] for name in data.files}, "index": np.array([4, 0, 2, 0])}


def run_other_cpus(directory: Path, checks: list[str]) -> dict[str, str]:
    """Writes the inputs of ``checks`` into ``directory`` and runs every check in one process per setting of
    ``OTHER_CPUS`` (all at once) into ``directory/<n>/``, n the setting's place in ``OTHER_CPUS``.
    Returns each setting's error: its exit status and the end of its stderr, or '' where it succeeded."""
    directory.mkdir(parents=True, exist_ok=True)
    for check in checks:
        np.savez(directory / f"{check}.in.npz", **inputs(check))

    def run(number: int, variables: dict[str, str]) -> str:
        target = directory / str(number)
        target.mkdir(exist_ok=True)
        result = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(directory), str(target), *checks],
                                env={**os.environ, **variables, "PYTHONPATH": str(ROOT)}, cwd=ROOT,
                                capture_output=True, text=True)
        return "" if result.returncode == 0 else f"exit status {result.returncode}: {result.stderr[-3000:]}"

    with ThreadPoolExecutor(max_workers=len(OTHER_CPUS)) as pool:
        errors = list(pool.map(run, range(len(OTHER_CPUS)), OTHER_CPUS.values()))
    return dict(zip(OTHER_CPUS, errors))


@dataclass(frozen=True)
class Runs:
    """The runs of ``run_other_cpus`` in ``directory``, and each setting's error ('' where it succeeded)."""

    directory: Path
    errors: dict[str, str]

    def compare(self, check: str, setting: str) -> tuple[dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray]]:
        """(the whole batch's fields of ``check`` computed in this process, the sub-batch's index, the other CPU's
        ``whole_*`` and ``part_*`` fields); fails the test where the other CPU's process failed."""
        import pytest  # noqa: PLC0415 (the worker does without)

        if self.errors[setting]:
            pytest.fail(f"{setting}: {self.errors[setting]}")
        data = dict(np.load(self.directory / f"{check}.in.npz"))
        state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
        here = fields(CHECKS[check].build(), state, data["d_eps"], CHECKS[check].tangent)
        number = list(OTHER_CPUS).index(setting)
        return here, data["index"], dict(np.load(self.directory / str(number) / f"{check}.out.npz"))


def main(source: str, target: str, *checks: str) -> None:
    for check in checks:
        np.savez(Path(target) / f"{check}.out.npz", **evaluate(check, np.load(Path(source) / f"{check}.in.npz")))


if __name__ == "__main__":
    main(*sys.argv[1:])
