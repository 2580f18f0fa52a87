"""python studies/screen_dobrany_density_families.py RESULT.json [--spreads 0,1,2,3] [--rule 35x12s] [--tag T]

A screen (no fit) of the density families: each material point as ``opening_spread.N_NODES`` families of initial
opening angles alpha0 + s x_j (alpha0_spread s; the Gauss-Legendre nodes of ``homogenization.material.
opening_spread``, weights g_j), every family renewed by the critical-state rule on its own void ratio
e_j = (1 + e0_j) J - 1, e0_j the set's map's void ratio of the family's alpha0 (the point's J, its strain and its
interlocking friction shared; ``calibration.renewal.PopulationRenewal``). A point of spread s is then a mixture of denser and looser sub-volumes: where a family
is looser than the renewal's alpha_c it renews with contractive cells while the denser ones dilate, so a specimen
nearer its critical state (the loose 200 kPa one) holds more contracting families than a dense one. The question:
does some s delay the predicted 200 kPa test's turn to dilation and its peak (the sand: dilative from 4.28 %, first
peak 6.33 %) with the fitted 50 and 100 kPa tests kept?

At a calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON, ``sensitivity_setup`` on
``--rule``), per spread and test: RMS abs(dq) / q_peak, RMS d eps_v, the most contraction and its strain, where
eps_v is back to 0, the first peak (a 5 % drop) and the highest q (``screen_dobrany_dilation_delay.shape``), and the
forward fallbacks. s = 0 is the point of one opening angle. Writes
studies/results/screen_dobrany_density_families_TAG.{json,txt}.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import RESULTS, dobrany_tests, sensitivity_setup  # noqa: E402
from screen_dobrany_dilation_delay import shape, text  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.material.opening_spread import NAME as SPREAD  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--spreads", default="0,1,2,3")
    parser.add_argument("--rule", default="35x12s")
    parser.add_argument("--tag", default="screen")
    args = parser.parse_args(argv)
    spreads = [float(v) for v in args.spreads.split(",")]
    _, params, settings = sensitivity_setup(args.result, args.rule, [()], (), kn_factor=None)
    tests = dobrany_tests()
    lines, rows = [], []

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    for name, test in tests.items():
        say(f"sand {name}: {text({**shape(test, test.observed['q'], test.observed['eps_v']), 'forward_fallbacks': 0})}")
    for s in spreads:
        for name, test in tests.items():
            t0 = time.perf_counter()
            with np.errstate(all="ignore"):
                c = forward.simulate(test, {**params, SPREAD: np.full(1, s)} if s else params, settings)
            row = {"spread": s, "test": name, **shape(test, c.q[0], c.eps_v[0]),
                   "forward_fallbacks": int(c.n_fallback[0]), "renewal_clips": int(c.n_renewal_clip[0]),
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            say(f"s = {s:g} deg, {name}: {text(row)}, renewal clips {row['renewal_clips']} ({row['seconds']:.0f} s)")
    out = RESULTS / f"screen_dobrany_density_families_{args.tag}"
    out.with_suffix(".json").write_text(json.dumps({"result": str(args.result), "rule": args.rule, "rows": rows},
                                                   indent=1))
    out.with_suffix(".txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
