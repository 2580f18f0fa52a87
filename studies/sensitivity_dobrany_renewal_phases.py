"""python studies/sensitivity_dobrany_renewal_phases.py RESULT.json [--phases cell,axis,mirror,mirror-spin] [--rule 15x4s] [--tag T]

The critical-state renewal's phase classes (``CriticalState.phases``: which cells are renewed together) at a Dobrany
calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON; every parameter the mean's) on its
forward model (the result's command's flags, on ``--rule``): the three drained tests for each phase rule. Prints per
rule and test RMS abs(dq) / q_peak, RMS d eps_v, the strain at the highest q (model / sand) and the swing of q, the
RMS of q minus its 11-point running mean [kPa] (the renewals' synchronised steps), then the rules in the order of
the mean RMS abs(dq) / q_peak over the result's two fitted tests. Writes
studies/results/sensitivity_dobrany_renewal_phases_TAG.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, print_ranking, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.material.critical_state import PHASES  # noqa: E402

WINDOW = 11
"""Points of the running mean that the swing of q is measured against."""


def swing(q: np.ndarray) -> float:
    """RMS of q minus its ``WINDOW``-point running mean, the ends left out [same unit as q]."""
    half = WINDOW // 2
    smooth = np.convolve(q, np.ones(WINDOW) / WINDOW, mode="same")
    return float(np.sqrt(np.mean((q[half:-half] - smooth[half:-half]) ** 2)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--phases", default=",".join(PHASES), help="phase rules, comma-separated")
    parser.add_argument("--rule", default="15x4s", help="orientation rule ORDERxSPINS[s]")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    phases = args.phases.split(",")
    if not set(phases) <= set(PHASES):
        parser.error(f"--phases {args.phases}: each one of {', '.join(PHASES)}")
    record, params, settings = sensitivity_setup(args.result, args.rule, [()], (), kn_factor=None)
    if settings.critical_state is None:
        parser.error(f"{args.result} was calibrated without the critical-state rule: no phases to vary")
    fitted, predicted = SPLITS[record["split"]]
    files = data_copies()
    rows = []
    for phase in phases:
        phased = replace(settings, critical_state=replace(settings.critical_state, phases=phase))
        for name in sorted(files, key=lambda f: read_test(files[f]).p0):
            test = read_test(files[name])
            with np.errstate(all="ignore"):
                c = forward.simulate(test, params, phased)
            m = metrics(test, c.q[0], c.eps_v[0])
            rows.append({"test": name, "phases": phase, **m, "swing_kpa": swing(np.asarray(c.q[0])) / 1e3,
                         "fallbacks": int(c.n_fallback[0])})
            print(f"{phase:12s} {args.rule} {name:15s}: RMS dq/qpk {m['rms_dq_over_qpeak']:.3f} RMS deps_v "
                  f"{100 * m['rms_deps_v']:.2f} % peak {100 * m['eps1_at_peak_model']:.2f} / "
                  f"{100 * m['eps1_at_peak_data']:.2f} % swing {rows[-1]['swing_kpa']:.1f} kPa, fallbacks "
                  f"{rows[-1]['fallbacks']}", flush=True)
    print(f"phase rules by the mean RMS abs(dq)/q_peak over the fitted tests {', '.join(fitted)} "
          f"(predicted {predicted}):")
    print_ranking(rows, ("phases",), fitted, lambda key: f"{key[0]:12s}")
    stem = f"sensitivity_dobrany_renewal_phases_{args.tag or record['split'].replace('+', '_')}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": args.rule,
                                                     "phases": phases, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
