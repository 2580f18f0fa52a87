"""python studies/certificate_drained_volume.py: the shipped meso-ANN models' volumetric strain in the certificate's
drained tests against the DEM's, which the certificate does not compare (it compares p and q).

For the planar and the spatial shipped model, the drained tests of the minimum certificate
(``homogenization.learning.certificate.tests_of``: compression and extension to 10 % at 1e-4, p0 = 2e5 and 1e6;
24 orientations in 2D, Lebedev 11 x 4 staggered spins in 3D), run as ``certify`` runs them (``run_test``). Per test:
the certificate's figure dq (max |q_ann - q_dem| over s = max(p0, max p_dem)), the largest |eps_v,ann - eps_v,dem|
over the shear stage (eps_v counted from its start, compression positive) and the DEM's largest |eps_v| there.
Prints one table; written to studies/results/certificate_drained_volume.txt.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from homogenization.ann import default_model_path
from homogenization.backends import make_cell_model
from homogenization.learning.certificate import requested_settings, run_test, tests_of
from warp_hcell.mesostructures.builders import mesostructure_arg

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "studies" / "results" / "certificate_drained_volume.txt"
CELLS = {2: "hcell:alpha0=55", 3: "hcell3d:alpha0=55"}


def shear_volume(record) -> np.ndarray:
    """eps_v [-] over the shear stage, counted from its start."""
    rows = record.stage != record.programme[0].label
    start = np.flatnonzero(rows)[0] - 1
    return record.eps_v[rows] - record.eps_v[start]


def main() -> None:
    lines = ["dim | test | dq (certificate) | max |d eps_v| | DEM's max |eps_v|"]
    print(lines[0], flush=True)
    for dim, spec in CELLS.items():
        meso = mesostructure_arg(spec).build(None)
        models = {"dem": make_cell_model("dem", dim=dim), "ann": make_cell_model("ann", dim=dim, model=default_model_path(dim))}
        settings = requested_settings(dim)
        for test, programme in tests_of(dim=dim):
            if test["kind"] != "drained":
                continue
            runs = {name: run_test(model, programme, meso, settings) for name, model in models.items()}
            dem, ann = runs["dem"], runs["ann"]
            rows = {name: r.stage != r.programme[0].label for name, r in runs.items()}
            scale = max(test["p0"], float(dem.p[rows["dem"]].max()))
            dq = float(np.abs(ann.q[rows["ann"]] - dem.q[rows["dem"]]).max()) / scale
            v_dem, v_ann = shear_volume(dem), shear_volume(ann)
            lines.append(f"{dim}D | {test['name']} | {100 * dq:.3f} % | {100 * np.abs(v_ann - v_dem).max():.4f} % | "
                         f"{100 * np.abs(v_dem).max():.3f} %")
            print(lines[-1], flush=True)
    RESULTS.write_text("# python studies/certificate_drained_volume.py (strains in % of the specimen; dq in % of s)\n"
                       + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
