"""python studies/screen_dobrany_density_families.py RESULT.json [--spreads 0,1,2,3] [--rule 35x12s] [--tag T]

A screen (no fit) of a mechanism patched here, not in the package: each material point as ``opening_spread.N_NODES``
families of initial opening angles alpha0 + s x_j (the Gauss-Legendre nodes of ``homogenization.material.
opening_spread``, weights g_j), every family renewed by the critical-state rule on its own void ratio
e_j = (1 + e0_j) J - 1, e0_j the set's map's void ratio of the family's alpha0 (the point's J, its strain and its
interlocking friction shared). A point of spread s is then a mixture of denser and looser sub-volumes: where a family
is looser than the renewal's alpha_c it renews with contractive cells while the denser ones dilate, so a specimen
nearer its critical state (the loose 200 kPa one) holds more contracting families than a dense one. The question:
does some s delay the predicted 200 kPa test's turn to dilation and its peak (the sand: dilative from 4.28 %, first
peak 6.33 %) with the fitted 50 and 100 kPa tests kept?

At a calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON, ``sensitivity_setup`` on
``--rule``), per spread and test: RMS abs(dq) / q_peak, RMS d eps_v, the most contraction and its strain, where
eps_v is back to 0, the first peak (a 5 % drop) and the highest q (``screen_dobrany_dilation_delay.shape``), and the
forward fallbacks. s = 0 is the package's model (checked against ``forward.simulate`` bit for bit). Writes
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

from homogenization.calibration import forward, renewal as rn  # noqa: E402
from homogenization.material import opening_spread  # noqa: E402
from homogenization.material.density import line_angle_deg  # noqa: E402

SPREAD = {"s": 0.0}
"""The spread [deg] that the patched population and renewal read (0: the package's model)."""


def _col(v):
    """A per-point parameter (n,) as a column (n, 1); a scalar as it is."""
    return np.asarray(v, dtype=np.float64)[:, None] if np.ndim(v) else v


def patch() -> None:
    """Families in ``forward.population`` and a family-wise ``PopulationRenewal`` (module docstring)."""
    population, renewal = forward.population, forward._renewal
    x, _ = opening_spread.nodes()
    k = x.size

    def families(full, settings, dim):
        if SPREAD["s"] == 0.0:
            return population(full, settings, dim)
        return population({**full, opening_spread.NAME: np.full(full["alpha0"].shape, SPREAD["s"])}, settings, dim)

    def family_renewal(full, settings, points):
        r = renewal(full, settings, points)
        if SPREAD["s"] != 0.0:
            m = r.density
            alpha = full["alpha0"][:, None] + SPREAD["s"] * x[None, :]
            r.family_e0 = (_col(m.e_max) - (m.alpha_loose_deg - alpha) / (m.alpha_loose_deg - m.alpha_dense_deg)
                           * (_col(m.e_max) - _col(m.e_min)))
        return r

    original = {"density_angle": rn.Renewal.density_angle, "fresh_angle": rn.PopulationRenewal.fresh_angle,
                "rate": rn.Renewal.rate, "_tick": rn.Renewal._tick,
                "cell_fresh_angle": rn.Renewal.cell_fresh_angle, "advance": rn.Renewal.advance}

    def density_angle(self, J):
        if not hasattr(self, "family_e0"):
            return original["density_angle"](self, J)
        m = self.density
        e = (1.0 + self.family_e0) * np.asarray(J)[:, None] - 1.0
        return line_angle_deg(e, _col(m.e_min), _col(m.e_max), m.alpha_dense_deg, m.alpha_loose_deg)

    def fresh_angle(self, J):
        if not hasattr(self, "family_e0"):
            return original["fresh_angle"](self, J)
        p, a = self.params, self.density_angle(J)
        angle = _col(p.alpha_c_deg) + _col(p.gain) * (a - _col(p.alpha_c_deg))
        return np.where(np.isfinite(angle), angle, _col(p.alpha_c_deg)).reshape(-1)

    def rate(self, J):
        if not hasattr(self, "family_e0"):
            return original["rate"](self, J)
        p = self.params
        excess = self.density_angle(J) - _col(p.alpha_c_deg)
        loose = p.rate_gain if p.rate_gain_loose is None else p.rate_gain_loose
        gain = np.where(excess > 0.0, _col(loose), _col(p.rate_gain))
        return (_col(p.rate) * np.exp(gain * excess)).reshape(-1)

    def per_cell(self):
        """Cells of one family of a point (its orientations); called on the family paths only."""
        return self.material.orient.n_cells // k

    def tick(self, strain, J):
        if not hasattr(self, "family_e0"):
            return original["_tick"](self, strain, J)
        d_local, increment = self.distortion_increment(strain)
        r = self.rate(J)
        cap = np.minimum(r.reshape(-1, k), _col(self.params.rate_max)).reshape(-1)
        return d_local, r, np.repeat(cap * np.repeat(increment, k), per_cell(self))

    def cell_fresh_angle(self, J, index):
        if not hasattr(self, "family_e0"):
            return original["cell_fresh_angle"](self, J, index)
        angle = np.clip(self.fresh_angle(J), self.params.alpha_min_deg, self.params.alpha_max_deg)
        return angle[index // per_cell(self)]

    def advance(self, state):
        if not hasattr(self, "family_e0"):
            return original["advance"](self, state)
        d_local, r, t = self._tick(state.strain, state.J)
        due = self._due(self.next_tick if self.params.in_increment else t)
        self.last_strain = np.array(state.strain)
        self.next_tick = t
        n_points, n = self.material.n_points, self.material.orient.n_cells
        self.capped = self.capped + (r.reshape(n_points, k) > _col(self.params.rate_max)).sum(axis=1)
        self.distortion = due["distortion"]
        self.merged = self.merged + np.maximum(due["after"] - due["before"] - 1.0, 0.0).reshape(n_points, n).sum(
            axis=1).astype(np.int64)
        per_family = due["due"].reshape(n_points * k, n // k).sum(axis=1)
        self.count = self.count + per_family.reshape(n_points, k).sum(axis=1)
        angle = self.fresh_angle(state.J)
        clipped = (angle < self.params.alpha_min_deg) | (angle > self.params.alpha_max_deg)
        self.clipped = self.clipped + (per_family * clipped).reshape(n_points, k).sum(axis=1)
        self.log.append((self.count, self.capped, self.clipped, self.merged))
        if self.params.in_increment or not due["due"].any():
            return state
        raise NotImplementedError("the families run the rule inside the increment only (in_increment)")

    forward.population, forward._renewal = families, family_renewal
    rn.Renewal.density_angle, rn.PopulationRenewal.fresh_angle, rn.Renewal.rate = density_angle, fresh_angle, rate
    rn.Renewal._tick, rn.Renewal.cell_fresh_angle, rn.Renewal.advance = tick, cell_fresh_angle, advance


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
    reference = {name: forward.simulate(test, params, settings) for name, test in tests.items()}
    patch()
    for s in spreads:
        SPREAD["s"] = s
        for name, test in tests.items():
            t0 = time.perf_counter()
            with np.errstate(all="ignore"):
                c = forward.simulate(test, params, settings)
            if s == 0.0:
                assert np.array_equal(c.q, reference[name].q, equal_nan=True), "s = 0 is not the package's model"
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
