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
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import grid_scan  # noqa: E402

GRID = "0.002,0.005:0.6666666666666666,0:0,10,15,20"
"""Default grid a_ref [-] : n [-] : s_m [-]."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--grid", default=GRID, help="A1,A2:N1,N2:S1,S2 (a_ref, n, s_m)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    grid = [[float(x) for x in part.split(",")] for part in args.grid.split(":")]
    tag = args.tag or json.loads(args.result.read_text())["split"].replace("+", "_")
    stem = f"sensitivity_dobrany_mobilisation_void_{tag}"
    grid_scan(args.result, ("mobilisation_strain", "mobilisation_exponent", "mobilisation_void_slope"),
              ("a_ref", "n", "s_m"), ("6.4f", ".2f", "4.1f"), grid, stem)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
