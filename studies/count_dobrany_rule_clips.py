"""python studies/count_dobrany_rule_clips.py [RESULT.json:RULE ...]

How often the forward model's rules fire at a Dobrany calibration's posterior mean (a ``calibration_dobrany_product.py``
result JSON, every setting of its command, on the orientation rule RULE, e.g. 35x12s): per test, the critical-state
renewal's renewals, capped rates and renewals made at a clipped fresh angle, the interlocking friction's clips
(``forward.Curves.n_clip``), the forward fallbacks and jumps. The renewal is read from the population it ran on
(``renewal.PopulationRenewal`` is wrapped here to keep it). Default: the 50 + 100 fit on 35 x 12 and the 50 + 200 fit
on 15 x 4 of docs/studies/calibration_dobrany_rule_convergence.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import RESULTS, dobrany_tests, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward, renewal as rn  # noqa: E402

DEFAULT = (f"{RESULTS}/calibration_dobrany_product_50_100_mv_n0_ms_cs05_kn08_35x12s.json:35x12s",
           f"{RESULTS}/calibration_dobrany_product_50_200_mobil_ms_15x4s.json:15x4s")


def main(argv: list[str]) -> int:
    kept = []
    built = rn.PopulationRenewal.__init__

    def keep(self, *args, **kwargs):
        built(self, *args, **kwargs)
        kept.append(self)

    rn.PopulationRenewal.__init__ = keep
    for spec in argv or DEFAULT:
        path, rule = spec.rsplit(":", 1)
        _, params, settings = sensitivity_setup(Path(path), rule, [()], (), kn_factor=None)
        for name, test in dobrany_tests().items():
            with np.errstate(all="ignore"):
                curves = forward.simulate(test, params, settings)
            r = kept[-1]
            print(f"{Path(path).stem} on {rule}, {name}: renewals {int(r.count[0])}, rate capped {int(r.capped[0])}, "
                  f"renewed at a clipped angle {int(r.clipped[0])}; interlocking clips {int(curves.n_clip[0])}; "
                  f"forward fallbacks {int(curves.n_fallback[0])}, jumps {int(curves.n_jump[0])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
