"""python studies/sensitivity_dobrany_void_lag.py RESULT.json [--grid G1,G2:K1,K2:S1,S2] [--tag T]

The interlocking's lag with a void-ratio factor (``calibration.interlocking``: gamma_r(p, e0) = gamma_r (p /
p_ref)^k exp(s (e0 - 0.55)), ``relax_strain`` gamma_r, ``relax_exponent`` k, ``relax_void_slope`` s, e0 the test's
void ratio) at a Dobrany calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON; its
"mean" values, every other parameter the mean's) on its forward model (the result's command's flags, Lebedev 15 x 4
staggered): the three drained tests, one batch per test, for the grid of (gamma_r, k, s). Prints per variant and
test RMS abs(dq) / q_peak, RMS d eps_v and the strain at the highest q (model / sand), then the variants in the order
of the mean RMS abs(dq) / q_peak over the result's two fitted tests (a start chosen from it does not see the
predicted test). Writes studies/results/sensitivity_dobrany_void_lag_TAG.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import grid_scan  # noqa: E402

GRID = "0.005,0.01,0.02:0,1.5:0,10,20,30"
"""Default grid gamma_r [-] : k [-] : s [-]."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--grid", default=GRID, help="G1,G2:K1,K2:S1,S2 (gamma_r, k, s)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    grid = [[float(x) for x in part.split(",")] for part in args.grid.split(":")]
    tag = args.tag or json.loads(args.result.read_text())["split"].replace("+", "_")
    stem = f"sensitivity_dobrany_void_lag_{tag}"
    grid_scan(args.result, ("relax_strain", "relax_exponent", "relax_void_slope"),
              ("gamma_r", "k", "s"), ("5.3f", ".2f", "4.1f"), grid, stem)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
