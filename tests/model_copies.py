"""A copy of the shipped 3D meso-ANN whose certificate a test can rewrite."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from homogenization.ann import default_model_path

SHIPPED_3D = default_model_path(3)


def shipped_3d_copy(folder: Path) -> tuple[Path, dict]:
    """(``folder/m.pt``, its metadata): the shipped 3D model and its out-of-distribution index copied into ``folder``,
    and the shipped JSON metadata read (write it to ``m.json`` after editing its certificate)."""
    model = folder / "m.pt"
    shutil.copy(SHIPPED_3D, model)
    shutil.copy(SHIPPED_3D.with_name(f"{SHIPPED_3D.stem}_ood.npz"), folder / "m_ood.npz")
    return model, json.loads(SHIPPED_3D.with_suffix(".json").read_text())
