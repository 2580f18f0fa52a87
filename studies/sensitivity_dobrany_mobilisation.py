"""python studies/sensitivity_dobrany_mobilisation.py RESULT.json [--rule 15x4s] [--tag T]

The friction mobilisation of the interlocking rule (``calibration.interlocking``, ``mobilisation_strain`` a_ref and
``mobilisation_start`` r0) at a Dobrany calibration's posterior mean (a ``calibration_dobrany_product.py`` result):
the three drained tests, one batch per test, for a grid of (a_ref, r0, kn factor), every other parameter the mean's.
Prints per variant and test RMS abs(dq) / q_peak, RMS d eps_v, strain at the highest q (model, sand), q model /
sand at 0.1 and 1 % of axial strain; writes studies/results/sensitivity_dobrany_mobilisation_TAG.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402

GRID = {"a_ref": (0.0, 0.002, 0.005, 0.01), "r0": (0.3, 0.6), "kn_factor": (1.0, 2.0)}
"""The variants: a_ref [-], r0 [-], kn factor [-] (a_ref = 0: r0 is not read, so only one r0)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--rule", default="15x4s")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    variants = [v for v in itertools.product(*GRID.values()) if v[0] > 0.0 or v[1] == GRID["r0"][0]]
    record, params, settings = sensitivity_setup(args.result, args.rule, variants,
                                                 ("mobilisation_strain", "mobilisation_start"))
    files = data_copies()
    rows = []
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        qd = test.observed["q"]
        for i, v in enumerate(variants):
            m = metrics(test, c.q[i], c.eps_v[i])
            ratio = [float(np.interp(e, test.eps1, c.q[i]) / np.interp(e, test.eps1, qd)) for e in (1e-3, 1e-2)]
            rows.append({"test": name, "a_ref": v[0], "r0": v[1], "kn_factor": v[2], **m,
                         "q_ratio_0.1%": ratio[0], "q_ratio_1%": ratio[1], "fallbacks": int(c.n_fallback[i])})
            print(f"{name:15s} a_ref {v[0]:6.3f} r0 {v[1]:.1f} kn x{v[2]:.0f}: RMS dq/qpk {m['rms_dq_over_qpeak']:.3f} "
                  f"RMS deps_v {100 * m['rms_deps_v']:.2f} % peak {100 * m['eps1_at_peak_model']:.2f} / "
                  f"{100 * m['eps1_at_peak_data']:.2f} % q/sand at 0.1 % {ratio[0]:.2f}, 1 % {ratio[1]:.2f}",
                  flush=True)
    stem = f"sensitivity_dobrany_mobilisation_{args.tag or record['split'].replace('+', '_')}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": args.rule, "rows": rows},
                                                     indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
