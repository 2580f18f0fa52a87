"""python studies/screen_dobrany_dilation_delay.py RESULT.json diagnose|renewal-state|stiffness-void|mean
                                                  [--values ...] [--scales ...] [--rule 15x4s] [--tag T]

Where the model's 200 kPa Dobrany test stops contracting, and a screen (no fit) of two mechanisms that could delay a
looser point's dilation, at a calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON;
``sensitivity_setup`` on ``--rule``, default Lebedev 15 x 4 staggered, every other parameter the mean's). Per run and test: RMS abs(dq) /
q_peak, RMS d eps_v, the strain at the most contraction (the largest eps_v, contraction positive) and where eps_v is
back to 0, the first peak of q (a 5 % drop, ``scan_dobrany_peak_strain.first_peak``), the highest q, forward fallbacks.
The model's curves are sampled on the data's eps1 (0.33 -> 0.50 -> 0.60 % between data points near the turn).

- ``diagnose``: the 200 kPa test with one thing changed at a time, grouped by the brief's three questions: the cells'
  opening angle (alpha0 set directly, the friction's e0 kept at the specimen's, with and without the renewal), the
  critical-state renewal (rate, gain, alpha_c, off), the interlocking friction (m, mobilisation, spread, phi_g), and
  the contact stiffness kn (found by the first three to be what sets the turn).
- ``renewal-state`` (candidate A, patched here, not in the package): the renewal reads the state relative to the
  interlocking's critical-state line: its void ratio e + w (e_c(p_ref) - e_c(p)) (``--mode all``: a critical void ratio
  that falls with p in the renewal too, w = 1 its state parameter carried to p_ref), or e + w max(e - e_c(p), 0)
  (``--mode loose``: only a looser-than-critical point renews looser), p and e of the accepted state.
- ``stiffness-void`` (candidate B): each test's kn times k exp(-s (e0 - 0.55)) (looser specimen, softer contacts; Hardin
  & Richart's F(e) = (2.17 - e)^2 / (1 + e) has d ln F / d e = -1.9 at e = 0.55), for s in ``--values`` and k in
  ``--scales`` (k stands for the refit's kn).
- ``mean``: the three tests at the mean itself (a fit's outcome), with the sand's numbers beside.

Every run ranks its variants by the mean RMS abs(dq) / q_peak over the result's FITTED tests. Writes
studies/results/screen_dobrany_dilation_delay_TAG.json (every row) and .txt (the printed lines).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, dobrany_tests, sensitivity_setup  # noqa: E402
from scan_dobrany_peak_strain import DROP_WIDE, first_peak  # noqa: E402

from homogenization.calibration import forward, interlocking as il, renewal as rn  # noqa: E402
from homogenization.material.density import current_void_ratio, line_angle_deg  # noqa: E402

E_REF = 0.55
"""Reference void ratio of candidate B's factor [-] (``interlocking.RELAX_VOID_REF``)."""
PATCH = {"w": 0.0, "mode": "all"}
"""Candidate A's weight and mode, read by the patched renewal (``patch_renewal``)."""


def patch_renewal() -> None:
    """Candidate A: ``PopulationRenewal.density_angle`` reads e + ``void_shift`` (per point, set by the interlocking from
    each accepted state, module docstring); no shift where PATCH's w is 0 (the package's rule)."""
    def density_angle(self, J):
        m = self.density
        e = current_void_ratio(self.e0, J) + getattr(self, "void_shift", 0.0)
        return line_angle_deg(e, m.e_min, m.e_max, m.alpha_dense_deg, m.alpha_loose_deg)

    original = il.InterlockingFriction.set_from

    def set_from(self, state):
        original(self, state)
        if self.inner is None:
            return
        p = np.maximum(self._mean(state.stress), 0.0)
        e_c = il.critical_void_ratio(p, self.e_gamma, self.lambda_c, self.xi, self.params.p_ref)
        e = current_void_ratio(self.e0, state.J)
        shift = (PATCH["w"] * (self.e_gamma - self.lambda_c - e_c) if PATCH["mode"] == "all"
                 else PATCH["w"] * np.maximum(e - e_c, 0.0))
        self.inner.void_shift = np.where(np.isfinite(shift), shift, 0.0)

    rn.PopulationRenewal.density_angle = density_angle
    il.InterlockingFriction.set_from = set_from


def shape(test, q: np.ndarray, eps_v: np.ndarray) -> dict:
    """The numbers of one curve (module docstring)."""
    e = test.eps1
    j = int(np.nanargmax(eps_v))
    back = np.flatnonzero((eps_v < 0.0) & (e > e[j]))
    m = metrics(test, q, eps_v)
    return {"rms_dq_over_qpeak": m["rms_dq_over_qpeak"], "rms_deps_v": m["rms_deps_v"],
            "most_contraction": float(eps_v[j]), "most_contraction_strain": float(e[j]),
            "dilative_from": float(e[back[0]]) if back.size else None,
            "first_peak_strain": float(e[first_peak(q, DROP_WIDE)]), "highest_strain": float(e[int(np.nanargmax(q))]),
            "highest_q": float(np.nanmax(q))}


def text(r: dict) -> str:
    back = "never" if r["dilative_from"] is None else f"{100 * r['dilative_from']:.2f} %"
    return (f"dq {r['rms_dq_over_qpeak']:.3f}, deps_v {100 * r['rms_deps_v']:.2f} %, most contraction "
            f"{100 * r['most_contraction']:.2f} % at {100 * r['most_contraction_strain']:.2f} %, eps_v < 0 from {back}, "
            f"first peak {100 * r['first_peak_strain']:.2f} %, highest q {r['highest_q'] / 1e3:.0f} kPa at "
            f"{100 * r['highest_strain']:.2f} %, fallbacks {r['forward_fallbacks']}")


def run_one(test, mean: dict, settings, over: dict | None = None, *, drop: tuple = (), alpha0: float | None = None,
            **changes) -> dict:
    """``shape`` of ``test`` at ``mean`` with ``over`` (CLI name -> value) changed, ``drop`` left out, the settings'
    ``changes``; ``alpha0``: the cell's opening angle set directly (the test run without its void ratio, the friction's
    e0 kept the specimen's; the renewal reads the angle's map void ratio)."""
    params = {k: np.array([v]) for k, v in {**mean, **(over or {})}.items() if k not in drop}
    run_test = test
    if alpha0 is not None:
        run_test = replace(test, void_ratio=None)
        params["alpha0"], params[forward.E0] = np.array([alpha0]), np.array([test.void_ratio])
    with np.errstate(all="ignore"):
        c = forward.simulate(run_test, params, replace(settings, **changes))
    return {**shape(test, c.q[0], c.eps_v[0]), "forward_fallbacks": int(c.n_fallback[0])}


def diagnose(tests: dict, mean: dict, settings, say) -> list[dict]:
    """The 200 kPa test one change at a time (module docstring)."""
    test = tests["cid_200kpa.csv"]
    sand = shape(test, test.observed["q"], test.observed["eps_v"])
    say(f"sand 200 kPa: most contraction {100 * sand['most_contraction']:.2f} % at "
        f"{100 * sand['most_contraction_strain']:.2f} %, eps_v < 0 from {100 * sand['dilative_from']:.2f} %, first peak "
        f"{100 * sand['first_peak_strain']:.2f} %")
    for name, t in tests.items():
        a0 = forward.density_alpha0(t, {k: np.array([v]) for k, v in mean.items()}, settings)[0]
        e_c = il.critical_void_ratio(t.p0, mean["e_gamma"], mean["lambda_c"], mean["xi_c"], il.P_REF)
        e_ac = mean["e_max"] - (55.3 - mean["alpha_c"]) / (55.3 - 47.0) * (mean["e_max"] - mean["e_min"])
        say(f"{name}: e0 {t.void_ratio:.4f}, map alpha0 {a0:.2f} deg (renewal's alpha_c {mean['alpha_c']:.2f} deg, "
            f"e {e_ac:.4f} there), interlocking e_c(p0) {float(e_c):.4f}")
    off = {"drop": ("alpha_c", "renewal_rate"), "critical_state": None}
    rule = settings.critical_state
    groups = {
        "the mean": [("the mean", {}, {})],
        "Q1 the cells' opening angle": (
            [(f"alpha0 {a:g} deg", {}, {"alpha0": a}) for a in (49.0, 50.5, 51.716, 52.5, 53.5, 55.3)]
            + [(f"no renewal, alpha0 {a:g} deg", {}, {"alpha0": a, **off}) for a in (51.716, 53.5, 55.3, 58.0, 60.0)]),
        "Q2 the renewal": [
            ("renewal_rate x0.1", {"renewal_rate": 0.1 * mean["renewal_rate"]}, {}),
            ("renewal_rate x3", {"renewal_rate": 3.0 * mean["renewal_rate"]}, {}),
            ("no renewal", {}, off), ("gain 0 (fresh cells at alpha_c)", {}, {"critical_state": replace(rule, gain=0.0)}),
            ("alpha_c 51 (the point looser than alpha_c)", {"alpha_c": 51.0}, {}), ("alpha_c 55", {"alpha_c": 55.0}, {})],
        "Q3 the interlocking": [
            ("interlocking_m 0 (phi_mu)", {"interlocking_m": 0.0}, {}), ("interlocking_m 4", {"interlocking_m": 4.0}, {}),
            ("no mobilisation", {"mobilisation_strain": 0.0}, {}), ("cell_spread 0", {"cell_spread": 0.0}, {}),
            ("phi_g 30", {"phi_g": 30.0}, {}), ("phi_g 45", {"phi_g": 45.0}, {}),
            ("no renewal, m 0, no mobilisation", {"interlocking_m": 0.0, "mobilisation_strain": 0.0}, off)],
        "Q4 the contact stiffness": [
            (f"kn x{f:g}{', no renewal' if o else ''}", {"kn": f * mean["kn"]}, o)
            for o in ({}, off) for f in (0.3, 0.5, 0.7, 1.5, 3.0)],
    }
    rows = []
    for group, items in groups.items():
        say(f"-- {group}")
        for label, over, how in items:
            how = dict(how)
            r = run_one(test, mean, settings, over, drop=how.pop("drop", ()), alpha0=how.pop("alpha0", None), **how)
            rows.append({"group": group, "variant": label, "test": "cid_200kpa.csv", **r})
            say(f"{label:44s} {text(r)}")
    return rows


def screen(tests: dict, mean: dict, settings, grid: list[tuple], kind: str, fitted: tuple, say) -> list[dict]:
    """Candidate A (``kind`` "all" or "loose": grid of (w,)) or B ("stiffness": grid of (s, k)) on the three tests,
    one line per variant; then the variants by the fitted tests' mean RMS abs(dq) / q_peak."""
    rows = []
    for g in grid:
        line = []
        for name, test in tests.items():
            if kind == "stiffness":
                factor = g[1] * np.exp(-g[0] * (test.void_ratio - E_REF))
                r = run_one(test, mean, settings, {"kn": factor * mean["kn"]})
                r["kn_factor"] = float(factor)
            else:
                PATCH["w"], PATCH["mode"] = g[0], kind
                r = run_one(test, mean, settings)
            rows.append({"variant": list(g), "test": name, **r})
            line.append(f"{name[4:-7]} kPa{' (kn x%.2f)' % r['kn_factor'] if kind == 'stiffness' else ''}: "
                        f"dq {r['rms_dq_over_qpeak']:.3f}, deps_v {100 * r['rms_deps_v']:.2f} %, turn "
                        f"{100 * r['most_contraction_strain']:.2f} %, first peak {100 * r['first_peak_strain']:.2f} %, "
                        f"fb {r['forward_fallbacks']}")
        label = f"s {g[0]:5.1f} k {g[1]:.2f}" if kind == "stiffness" else f"{kind} w {g[0]:5.2f}"
        fit = np.mean([r["rms_dq_over_qpeak"] for r in rows[-3:] if r["test"] in fitted])
        say(f"{label}: fitted mean {fit:.4f} | " + " | ".join(line))
        for r in rows[-3:]:
            r["fitted_mean"] = float(fit)
    say("by the fitted tests' mean RMS abs(dq)/q_peak:")
    ranked = sorted({tuple(r["variant"]): r["fitted_mean"] for r in rows}.items(), key=lambda kv: kv[1])
    say("  " + "; ".join(f"{v}: {f:.4f}" for v, f in ranked))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("what", choices=("diagnose", "renewal-state", "stiffness-void", "mean"))
    parser.add_argument("--values", default="", help="renewal-state: weights w; stiffness-void: slopes s")
    parser.add_argument("--scales", default="1", help="stiffness-void: kn factors k")
    parser.add_argument("--mode", choices=("all", "loose"), default="all", help="renewal-state's form")
    parser.add_argument("--rule", default="15x4s", help="ORDERxSPINS[a|s]: the orientation rule")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    if not args.result.is_file():
        print(f"error: no file {args.result}", file=sys.stderr)
        return 2
    record, _, settings = sensitivity_setup(args.result, args.rule, [(0.0,)], (), kn_factor=None)
    mean = record["mean"]["values"]
    fitted, predicted = SPLITS[record["split"]]
    tests = dobrany_tests()
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        print(line, flush=True)

    started = time.perf_counter()
    say(f"{args.what} at the mean of {args.result.name} (fitted {', '.join(fitted)}; predicted {predicted}), {args.rule}")
    if args.what == "mean":
        rows = []
        for name, test in tests.items():
            r = {"test": name, **run_one(test, mean, settings)}
            sand = shape(test, test.observed["q"], test.observed["eps_v"])
            rows.append({**r, "sand": sand})
            say(f"{name:15s} model: {text(r)}")
            say(f"{'':15s} sand:  most contraction {100 * sand['most_contraction']:.2f} % at "
                f"{100 * sand['most_contraction_strain']:.2f} %, first peak {100 * sand['first_peak_strain']:.2f} %")
    elif args.what == "diagnose":
        rows = diagnose(tests, mean, settings, say)
    elif args.what == "renewal-state":
        patch_renewal()
        rows = screen(tests, mean, settings, [(float(w),) for w in args.values.split(",")], args.mode, fitted, say)
    else:
        grid = [(float(s), float(k)) for s in args.values.split(",") for k in args.scales.split(",")]
        rows = screen(tests, mean, settings, grid, "stiffness", fitted, say)
    say(f"wall {time.perf_counter() - started:.0f} s")
    stem = f"screen_dobrany_dilation_delay_{args.tag or args.what}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": args.rule, "what": args.what,
                                                      "rows": rows}, indent=1))
    (RESULTS / f"{stem}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
