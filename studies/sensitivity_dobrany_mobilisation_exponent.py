"""python studies/sensitivity_dobrany_mobilisation_exponent.py

The pressure exponent of the mobilisation strain a(p) = a_ref (p / p_ref)^x (``calibration.interlocking``,
``MOBILISATION_EXPONENT``, 2/3 in the product) at the posterior means of the two Dobrany fits with the mobilisation
(``calibration_dobrany_product.py --tag mobil_15x4s``, their run folders under runs/dobrany_product/): the three
drained tests with x = 2/3, 1/3 and 0 (``mobilisation_exponent``, per set), every parameter the mean's,
on the calibration's forward model. Prints per test RMS abs(dq) / q_peak, RMS d eps_v, the strain at the highest q
(model / sand) and the highest q [kPa] (model / sand).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RUNS, data_copies  # noqa: E402

from homogenization.calibration import forward, posterior as post_mod  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402


def main() -> int:
    files = data_copies()
    for split in ("50_100", "50_200"):
        post = post_mod.read_posterior(RUNS / f"{split}_mobil_15x4s")
        mean = {k: np.array([v]) for k, v in post.mean.items()}
        for x in (2 / 3, 1 / 3, 0.0):
            out = []
            for name in sorted(files, key=lambda f: read_test(files[f]).p0):
                test = read_test(files[name])
                with np.errstate(all="ignore"):
                    c = forward.simulate(test, {**mean, "mobilisation_exponent": np.array([x])}, post.forward)
                m = metrics(test, c.q[0], c.eps_v[0])
                out.append(f"{name[4:7]} {m['rms_dq_over_qpeak']:.3f} {100 * m['rms_deps_v']:.2f}% pk "
                           f"{100 * m['eps1_at_peak_model']:.2f}/{100 * m['eps1_at_peak_data']:.2f} "
                           f"({m['q_peak_model'] / 1e3:.0f}/{m['q_peak_data'] / 1e3:.0f})")
            print(split, f"exponent {x:.3f}:", " | ".join(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
