"""The meso-ANN backend and what polices it: ``--backend ann`` (``homogenization.backends.BACKENDS``).

- ``cell``: ``AnnCell`` (``AnnCell3D``), the ``warp_hcell.core.contract.CellModel`` whose increments a
  trained ``training.network.MesoNet`` decides, with or without equilibrium corrections; stepping only.
- ``policy``: whether the model may be used (``certificate_problem``), what a run records of it
  (``model_record``) and ``CertificatePolicy``, the certificate and its envelope beside a cell.
- ``ood``: ``OodMonitor``, the out-of-distribution checks of a cell's start states (``training.ood``).
- ``escalation``: ``DemEscalation``, the DEM's increment in the cells a released grain leaves to it.
- ``records`` and ``envelope``: the certificate as a record, the minimum certificate and what a
  certificate covers.

The learning loop that writes certificates (``homogenization.learning``) sits above this package; nothing
here imports it. Sign convention: compression and contraction positive.
"""

from __future__ import annotations

from pathlib import Path

DEFAULT_MODELS = {2: "ann_default.pt", 3: "ann3d_default.pt"}
"""File names of the models shipped in ``homogenization/data``, by cell dimension (metadata in the ``.json`` beside)."""
RANGE_MODELS = {2: True, 3: False}
"""Whether the shipped model of cells of each dimension covers a range of opening angles alpha0 (the 3D
one is trained at alpha0 = 55 deg only), as calibrating alpha0 needs."""


def default_model_path(dim: int = 2) -> Path:
    """Path of the shipped default model state_dict of cells of dimension ``dim`` (its metadata sits next to it);
    KeyError for a dimension without one."""
    return Path(__file__).resolve().parents[1] / "data" / DEFAULT_MODELS[dim]
