"""python studies/screen_dobrany_state_map.py RESULT.json [--weights 0,0.2,0.35,0.5,0.7,1] [--tag T]

Screen (no fit) of the interlocking's state map (``map_state_weight`` w: each test's cell built at the void-ratio
map's alpha0 of e0 + w lambda_c ((p0 / p_ref)^xi_c - 1), ``interlocking.state_map_void_ratio``) at a Dobrany
calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON; ``sensitivity_setup`` on Lebedev
15 x 4 staggered, every other parameter the mean's): the three drained tests, all weights in one batch per test.
Per weight and test: the mapped void ratio (NaN curves where the mean's [e_min, e_max] does not hold it, counted),
RMS abs(dq) / q_peak, RMS d eps_v, the strain at the first peak (2 % and 5 % drops) and at the highest q, model and
sand (``scan_dobrany_peak_strain.row``), the forward fallbacks. Then the weights in the order of the mean RMS
abs(dq) / q_peak over the result's FITTED tests (``calibration_dobrany_product.print_ranking``), so that a choice
made from it does not see the predicted test. Writes studies/results/screen_dobrany_state_map_TAG.json (every row)
and .txt (the printed lines).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, print_ranking, sensitivity_setup  # noqa: E402
from scan_dobrany_peak_strain import row  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.interlocking import state_map_void_ratio  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--weights", default="0,0.2,0.35,0.5,0.7,1")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    weights = [float(w) for w in args.weights.split(",")]
    if not args.result.is_file() or not all(-2.0 <= w <= 2.0 for w in weights):
        print(f"error: no file {args.result}, or a weight outside [-2, 2]", file=sys.stderr)
        return 2
    record, params, settings = sensitivity_setup(args.result, "15x4s", [(w,) for w in weights],
                                                 (forward.MAP_STATE,), kn_factor=None)
    mean = record["mean"]["values"]
    fitted, predicted = SPLITS[record["split"]]
    files = data_copies()
    rows, lines = [], []

    def say(text: str) -> None:
        lines.append(text)
        print(text, flush=True)

    started = time.perf_counter()
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        e_map = state_map_void_ratio(test.void_ratio, test.p0, np.array(weights), mean["lambda_c"], mean["xi_c"],
                                     settings.interlocking.p_ref)
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        for i, w in enumerate(weights):
            unmapped = not np.all(np.isfinite(c.q[i]))
            r = {"weight": w, "e_map": float(e_map[i]), "unmapped": unmapped,
                 **(row(f"w={w:g}", name, test, mean, c.q[i], c.eps_v[i], int(c.n_fallback[i])) if not unmapped else
                    {"test": name}),
                 **(metrics(test, c.q[i], c.eps_v[i]) if not unmapped else {})}
            rows.append(r)
            say(f"{name:15s} e0 {test.void_ratio:.3f} w {w:4.2f}: e_map {e_map[i]:.4f}" + (
                " outside the map: NaN curves" if unmapped else
                f", dq {r['rms_dq_over_qpeak']:.3f}, deps_v {100 * r['rms_deps_v']:.2f} %, first peak "
                f"{100 * r['first_peak_strain']:.2f} (5 %: {100 * r['first_peak_wide_strain']:.2f}) / sand "
                f"{100 * r['sand_first_peak_strain']:.2f} %, highest q {r['highest_q'] / 1e3:.0f} kPa at "
                f"{100 * r['highest_strain']:.2f} / {100 * r['sand_highest_strain']:.2f} %, e/e_c at first peak "
                f"{r['void_over_critical_at_first_peak']:.3f}, fallbacks {r['forward_fallbacks']}"))
    say(f"wall {time.perf_counter() - started:.0f} s; {sum(r['unmapped'] for r in rows)} unmapped curves")
    say(f"weights by the mean RMS abs(dq)/q_peak over the fitted tests {', '.join(fitted)} (predicted {predicted}):")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        print_ranking([r for r in rows if not r["unmapped"]], ("weight",), list(fitted), lambda key: f"w {key[0]:4.2f}")
    for item in text.getvalue().splitlines():
        say(item)
    stem = f"screen_dobrany_state_map_{args.tag or args.result.stem}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": "15x4s", "weights": weights,
                                                      "rows": rows}, indent=1))
    (RESULTS / f"{stem}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
