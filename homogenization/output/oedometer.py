"""What an oedometric (K0) test reports: vertical and horizontal stress, K0 and volumetric strain of a
3D ``Record`` (axis 1 vertical; programme ``element_test.programme.oedometric``).

Sign convention: compression and contraction positive; stresses [Pa], strains [-].
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from homogenization.element_test.record import Record
from homogenization.material.invariants import volumetric_strain_3d

FILE = "oedometer.csv"
"""Name of the oedometer table written beside curve.csv."""
COLUMNS = ("stage", "eps_a", "eps_v", "sigma_v", "sigma_h", "K0")
"""Columns of ``FILE``."""


def columns(record: Record) -> dict[str, np.ndarray]:
    """The oedometer quantities of a 3D record, each shape (n,): ``eps_a`` = eps11, ``eps_v`` =
    eps11 + eps22 + eps33 (small strain), ``sigma_v`` = sigma11, ``sigma_h`` = (sigma22 + sigma33) / 2,
    ``K0`` = sigma_h / sigma_v (NaN where sigma_v <= 0)."""
    if record.eps33 is None or record.sigma33 is None:
        raise ValueError("an oedometer record needs a 3D run (components 11, 22, 33)")
    sigma_v = np.asarray(record.sigma11, dtype=float)
    sigma_h = 0.5 * (np.asarray(record.sigma22) + np.asarray(record.sigma33))
    with np.errstate(divide="ignore", invalid="ignore"):
        k0 = np.where(sigma_v > 0.0, sigma_h / sigma_v, np.nan)
    return {"stage": np.asarray(record.stage), "eps_a": np.asarray(record.eps11, dtype=float),
            "eps_v": volumetric_strain_3d(record.eps11, record.eps22, record.eps33),
            "sigma_v": sigma_v, "sigma_h": sigma_h, "K0": k0}


def write_csv(path: Path, record: Record) -> None:
    """Write ``columns(record)`` to ``path`` (header ``COLUMNS``, one row per increment)."""
    table = columns(record)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for i in range(table["eps_a"].size):
            writer.writerow([table["stage"][i], *(f"{table[name][i]:.10g}" for name in COLUMNS[1:])])
