"""python studies/peaks_dobrany_variants.py RESULT.json 'VARIANTS' [--tag T]

Where each Dobrany test peaks at a calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON;
its "mean" values) with some of its interlocking parameters changed, on its forward model (Lebedev 15 x 4
staggered). VARIANTS is a JSON list of objects, CLI name -> value (``{}``: the mean itself), e.g.
'[{}, {"mobilisation_void_slope": 0}, {"relax_strain": 0.01, "relax_void_slope": 30}]'; a parameter the mean lacks is
the forward settings' interlocking's. Prints per test and variant: RMS abs(dq) / q_peak, RMS d eps_v, the first local
maximum of q (kPa at strain %), the highest q, the sand's peak, q model / sand [kPa] at 1, 3.5, 6.3 and 10 % strain,
and the forward model's fallbacks. Writes studies/results/peaks_dobrany_variants_TAG.txt (the same lines).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.interlocking import FIELDS  # noqa: E402

STRAINS = (0.01, 0.035, 0.063, 0.10)
"""Strains [-] at which q is printed (the 200 kPa test's first percent, two peaks of the sand, the decline)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("variants", type=json.loads)
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    variants = list(args.variants)
    _, params, settings = sensitivity_setup(args.result, "15x4s", [()] * len(variants), (), kn_factor=None)
    for name in sorted({k for v in variants for k in v}):
        base = params[name][0] if name in params else getattr(settings.interlocking, FIELDS[name])
        params[name] = np.array([float(v.get(name, base)) for v in variants])
    files = data_copies()
    lines = []
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        e, q_data = test.eps1, test.observed["q"]
        for i, variant in enumerate(variants):
            q = c.q[i]
            m = metrics(test, q, c.eps_v[i])
            local = [j for j in range(1, len(q) - 1) if q[j] >= q[j - 1] and q[j] > q[j + 1]]
            first = local[0] if local else int(np.argmax(q))
            at = " ".join(f"{q[k] / 1e3:.0f}/{q_data[k] / 1e3:.0f}" for k in np.searchsorted(e, STRAINS))
            lines.append(f"{name} e0 {test.void_ratio:.3f} {json.dumps(variant) if variant else 'mean'}: RMS dq/qpk "
                         f"{m['rms_dq_over_qpeak']:.3f}, RMS deps_v {100 * m['rms_deps_v']:.2f} %; first peak "
                         f"{q[first] / 1e3:.0f} kPa at {100 * e[first]:.2f} %, highest {q.max() / 1e3:.0f} at "
                         f"{100 * e[np.argmax(q)]:.2f} % (sand {q_data.max() / 1e3:.0f} at "
                         f"{100 * e[np.argmax(q_data)]:.2f} %); q model/sand [kPa] at 1/3.5/6.3/10 %: {at}; "
                         f"fallbacks {int(c.n_fallback[i])}")
            print(lines[-1], flush=True)
    stem = f"peaks_dobrany_variants_{args.tag or Path(args.result).stem}"
    (RESULTS / f"{stem}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
