"""python studies/sensitivity_dobrany_mobilisation_void.py RESULT.json [--grid A1,A2:N1,N2:S1,S2] [--tag T]

The interlocking's mobilisation strain with a void-ratio factor (``calibration.interlocking``: a(p, e0) = a_ref (p /
p_ref)^n exp(s_m (e0 - 0.55)), ``mobilisation_strain`` a_ref, ``mobilisation_exponent`` n,
``mobilisation_void_slope`` s_m, e0 the test's void ratio) at a Dobrany calibration's posterior mean (a
``calibration_dobrany_product.py`` result JSON with the mobilisation; its "mean" values, every other parameter the
mean's) on its forward model (the result's command's flags, Lebedev 15 x 4 staggered): the three drained tests, one
batch per test, for the grid of (a_ref, n, s_m). Prints per variant and
test RMS abs(dq) / q_peak, RMS d eps_v and the strain at the highest q (model / sand), then the variants in the order
of the mean RMS abs(dq) / q_peak over the result's two fitted tests (a start chosen from it does not see the
predicted test). Writes studies/results/sensitivity_dobrany_mobilisation_void_TAG.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, print_ranking, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402

GRID = "0.002,0.005:0.6666666666666666,0:0,10,15,20"
"""Default grid a_ref [-] : n [-] : s_m [-]."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--grid", default=GRID, help="A1,A2:N1,N2:S1,S2 (a_ref, n, s_m)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    grid = [[float(x) for x in part.split(",")] for part in args.grid.split(":")]
    variants = list(itertools.product(*grid))
    record, params, settings = sensitivity_setup(args.result, "15x4s", variants,
                                                 ("mobilisation_strain", "mobilisation_exponent",
                                                  "mobilisation_void_slope"), kn_factor=None)
    fitted, predicted = SPLITS[record["split"]]
    files = data_copies()
    rows = []
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        started = time.perf_counter()
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        for i, v in enumerate(variants):
            m = metrics(test, c.q[i], c.eps_v[i])
            rows.append({"test": name, "a_ref": v[0], "n": v[1], "s_m": v[2], **m, "fallbacks": int(c.n_fallback[i])})
            print(f"{name:15s} e0 {test.void_ratio:.3f} a_ref {v[0]:6.4f} n {v[1]:.2f} s_m {v[2]:4.1f}: RMS dq/qpk "
                  f"{m['rms_dq_over_qpeak']:.3f} RMS deps_v {100 * m['rms_deps_v']:.2f} % peak "
                  f"{100 * m['eps1_at_peak_model']:.2f} / {100 * m['eps1_at_peak_data']:.2f} %, fallbacks "
                  f"{int(c.n_fallback[i])}", flush=True)
        print(f"  ({len(variants)} variants in {time.perf_counter() - started:.0f} s)", flush=True)
    print(f"variants by the mean RMS abs(dq)/q_peak over the fitted tests {', '.join(fitted)} (predicted {predicted}):")
    print_ranking(rows, ("a_ref", "n", "s_m"), fitted, lambda key: f"a_ref {key[0]:6.4f} n {key[1]:.2f} s_m {key[2]:4.1f}")
    stem = f"sensitivity_dobrany_mobilisation_void_{args.tag or record['split'].replace('+', '_')}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "grid": grid, "rows": rows},
                                                    indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
