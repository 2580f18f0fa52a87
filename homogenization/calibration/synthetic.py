"""Synthetic measurements at known parameter values: the data of a calibrator's check on a known truth.

``synthetic_test(kind, p0, eps1, channels, truth, settings, noise, rng)`` runs the forward model
(``forward.simulate``: the DEM or the closed form, at the settings given, usually finer than a
calibration's) at ``truth`` and adds independent Gaussian noise of ``noise`` x each clean channel's
largest abs value to every point, as tests/data/calibration/make_synthetic.py does.
``write_test(path, test, comment)`` writes it in the format ``data.read_test`` reads.
Units: stresses [N/m] (2D) or [Pa] (3D), strains [-], compression positive.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from homogenization.calibration.data import TEST_KINDS, Measurement
from homogenization.calibration.forward import ForwardSettings, simulate


def synthetic_test(kind: str, p0: float, eps1: np.ndarray, channels: Sequence[str], truth: Mapping[str, float],
                   settings: ForwardSettings, noise: float, rng: np.random.Generator,
                   name: str | None = None) -> tuple[Measurement, dict[str, np.ndarray]]:
    """A noisy measurement of test ``kind`` (a value of ``data.TEST_KINDS``) and its clean curves.

    Args:
        p0: confining pressure [N/m in 2D, Pa in 3D].
        eps1: axial strains of the points [-], shape (k,), > 0, increasing.
        channels: the channels measured ("q", "p", "eps_v").
        truth: parameter values (``forward.PARAMETERS`` names, CLI units); the others are ``settings.fixed``.
        settings: forward model that makes the clean curves (backend, orientations, increments).
        noise: noise sd as a fraction of each clean channel's largest abs value [-].
        rng: source of the noise (one standard normal per point and channel, in channel order).

    Returns:
        The measurement (path: ``name``) and channel -> clean curve, shape (k,).
    """
    dim, drained = next(key for key, value in TEST_KINDS.items() if value == kind)
    name = name or f"{kind}.csv"
    shell = Measurement(name, Path(name), drained, float(p0), np.asarray(eps1, dtype=np.float64), {}, dim)
    curves = simulate(shell, {k: np.array([float(v)]) for k, v in truth.items()}, settings)
    clean = {c: curves.channel(c)[0] for c in channels}
    observed = {c: v + noise * float(np.max(np.abs(v))) * rng.standard_normal(v.size) for c, v in clean.items()}
    return Measurement(name, Path(name), drained, float(p0), shell.eps1, observed, dim), clean


def write_test(path: Path, test: Measurement, comment: str = "") -> None:
    """``test`` as a calibration CSV (``data`` module format) at ``path``; ``comment``: one more comment line."""
    lines = [f"# test = {test.kind}", f"# p0 = {test.p0:.10g}"] + ([f"# {comment}"] if comment else [])
    lines += [f"# void_ratio = {test.void_ratio:.10g}"] if test.void_ratio is not None else []
    lines.append(",".join(("eps1", *test.observed)))
    table = np.stack([test.eps1, *test.observed.values()], axis=1)
    lines += [",".join(f"{v:.10g}" for v in row) for row in table.tolist()]
    Path(path).write_text("\n".join(lines) + "\n")
