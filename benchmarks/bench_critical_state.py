"""Does the critical-state renewal (``homogenization.material.critical_state``) give the closed form a critical
state? Drained loose and dense tests at two pressures to 40 % axial strain, in 2D and 3D, and undrained tests.

Prints, per dimension, pressure and initial state: q/p and e at the end, the rates over the last 10 % of axial
strain (least-squares slopes: abs(dq/deps1)/p and abs(d eps_v/d eps1)), the renewals made, and the acceptance
checks (rates <= 0.05 and 0.01, end stress ratios within 5 %, end void ratios within 0.02); the undrained
tests' end (p, e), from the same two states and from alpha_c -+ 2 deg, against the line e = e_G - lambda ln p
through the drained ends. Writes
benchmarks/results/critical_state.{txt,json,png}.

    python benchmarks/bench_critical_state.py [--increment 2e-3] [--orientations 360] [--order 17 --spins 8] [--tag T]
    python benchmarks/bench_critical_state.py --dem-check      # DEM vs closed form, rule on, short 2D and 3D tests
    python benchmarks/bench_critical_state.py --shear-check    # 3D shear stresses per phase rule

The undrained ends at increments 2e-3, 1e-3 and 5e-4 (``--increment``, ``--tag``) show the rule's convergence.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.element_test import driver, programme as pg
from homogenization.material.critical_state import DEFAULTS, PHASES, CriticalState
from homogenization.material.density import default_map
from warp_hcell.mesostructures.hcell import plain_h_cell

RESULTS = Path(__file__).resolve().parent / "results"
PARAMS = DEFAULTS
"""The rule's parameters per dimension (the module's measured DEFAULTS)."""
STATES = {2: (48.0, 56.0), 3: (48.0, 56.0)}
"""Dense and loose initial opening angles [deg] per dimension (8 deg apart)."""
PRESSURES = (1e5, 4e5)
"""Confining pressures [N/m in 2D, Pa in 3D]."""
EPS = 0.4


def run(dim: int, alpha0: float, p0: float, test: str, args, params: CriticalState | None, backend: str = "analytical"):
    """The record of one test with the rule ``params`` (None: plain)."""
    model = make_cell_model(backend, dim=dim)
    if dim == 2:
        prog = pg.biaxial(p0, EPS, args.increment, drained=test == "drained")
        extra = {"n_orientations": args.orientations}
    else:
        prog = pg.triaxial(p0, EPS, args.increment, test=test)
        extra = {"lebedev_order": args.order, "n_spins": args.spins}
    return driver.run(model, prog, mesostructure=plain_h_cell(dim, alpha0), progress=False, critical_state=params,
                      **extra)


def slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y(x)."""
    return float(np.polyfit(x, y, 1)[0])


def summary(record, dim: int, alpha0: float) -> dict:
    """End values and last-10 % rates of the shear stage of ``record``."""
    shear = record.stage == "shear"
    e1 = record.eps11[shear] - record.eps11[shear][0]
    ev = sum(getattr(record, f"eps{c}{c}")[shear] for c in "123"[:dim])
    ev = ev - ev[0]
    q, p, J = record.q[shear], record.p[shear], record.J[shear]
    e0 = default_map(dim).void_ratio(alpha0)
    e = (1.0 + e0) * J - 1.0
    last = e1 >= e1[-1] - 0.1
    renewals = record.diagnostics.get("critical_state_renewals")
    return {"dim": dim, "alpha0": alpha0, "e0": e0, "q_over_p": float(q[-1] / p[-1]), "e": float(e[-1]),
            "p": float(p[-1]), "dq_rate": abs(slope(e1[last], q[last])) / float(p[-1]),
            "dv_rate": abs(slope(e1[last], ev[last])),
            "renewals": int(np.nanmax(renewals)) if renewals is not None else 0,
            "rate_capped": int(np.nanmax(record.diagnostics.get("critical_state_rate_capped", [0]))),
            "angle_clipped": int(np.nanmax(record.diagnostics.get("critical_state_angle_clipped", [0]))),
            "merged": int(np.nanmax(record.diagnostics.get("critical_state_merged", [0]))),
            "curve": {"eps1": e1[::5].tolist(), "q_over_p": (q / p)[::5].tolist(), "e": e[::5].tolist(),
                      "p": p[::5].tolist()}}


def dem_check(args) -> int:
    """DEM and closed form with the rule (DEFAULTS at rate 400) on short drained tests, 2D and 3D; prints the largest
    normal-stress gap / p0 and writes benchmarks/results/critical_state_dem.txt."""
    cases = ((2, pg.biaxial(2e5, 0.01, 1e-3, drained=True), 2e5, {"n_orientations": 12}, "12 orientations"),
             (3, pg.triaxial(1e5, 0.01, 1e-3, test="drained"), 1e5, {"lebedev_order": 5, "n_spins": 4},
              "Lebedev 5 x 4 spins"))
    lines = []
    for dim, prog, p0, extra, label in cases:
        out = {}
        for backend in ("analytical", "dem"):
            start = time.perf_counter()
            rec = driver.run(make_cell_model(backend, dim=dim), prog, mesostructure=plain_h_cell(dim, 52.0),
                             progress=False, critical_state=replace(DEFAULTS[dim], rate=400.0), **extra)
            out[backend] = (rec, time.perf_counter() - start)
        a, d = out["analytical"][0], out["dem"][0]
        gap = max(np.max(np.abs(getattr(a, f"sigma{c}{c}") - getattr(d, f"sigma{c}{c}"))) for c in "123"[:dim]) / p0
        lines.append(f"{dim}D DEM vs closed form, rule on ({label}, drained to 1 %, p0 = {p0:g}): largest normal-stress "
                     f"gap {gap:.2e} p0; renewals {np.nanmax(a.diagnostics['critical_state_renewals']):.0f} / "
                     f"{np.nanmax(d.diagnostics['critical_state_renewals']):.0f}; {out['analytical'][1]:.1f} s / "
                     f"{out['dem'][1]:.1f} s")
        print(lines[-1])
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "critical_state_dem.txt").write_text("\n".join(lines) + "\n")
    return 0


def shear_check(args) -> int:
    """3D shear stresses under the rule with each phase rule (``PHASES``) and without it: per test, the largest
    abs(sigma_23, sigma_13, sigma_12) / p over the shear stage and the last-10 % q rate; writes
    benchmarks/results/critical_state_shear.txt."""
    lines = [f"3D shear stresses, closed form, Lebedev {args.order} x {args.spins} spins, increments {args.increment:g}, "
             f"p0 1e5, to {EPS:.0%}; DEFAULTS[3] with each phase rule",
             "phases       test       alpha0  max|shear|/p  |dq/de1|/p  q/p end  e end   renewals"]
    print("\n".join(lines), flush=True)
    for phases in (None,) + PHASES:
        params = None if phases is None else replace(DEFAULTS[3], phases=phases)
        for alpha0, test in ((48.0, "drained"), (56.0, "drained"), (56.0, "undrained")):
            rec = run(3, alpha0, 1e5, test, args, params)
            s = summary(rec, 3, alpha0)
            shear = rec.stage == "shear"
            worst = max(np.max(np.abs(getattr(rec, c)[shear] / rec.p[shear])) for c in ("sigma23", "sigma13", "sigma12"))
            lines.append(f"{phases or 'plain':<12} {test:<10} {alpha0:<7g} {worst:<13.4f} {s['dq_rate']:<11.3f} "
                         f"{s['q_over_p']:<8.3f} {s['e']:.3f}   {s['renewals']}")
            print(lines[-1], flush=True)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "critical_state_shear.txt").write_text("\n".join(lines) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--increment", type=float, default=2e-3)
    parser.add_argument("--orientations", type=int, default=360)
    parser.add_argument("--order", type=int, default=17)
    parser.add_argument("--spins", type=int, default=8)
    parser.add_argument("--dims", default="2,3")
    parser.add_argument("--pressures", default=None, help="comma-separated p0 of the drained pairs (default 1e5,4e5; "
                        "the undrained tests start from the first); needs --tag")
    parser.add_argument("--no-undrained", action="store_true", help="the drained pairs only")
    parser.add_argument("--dem-check", action="store_true")
    parser.add_argument("--shear-check", action="store_true", help="3D shear stresses per phase rule")
    parser.add_argument("--tag", default="", help="suffix of the output files' names (e.g. _increment_1e-3)")
    parser.add_argument("--plain", action="store_true", help="the plain cells (no rule); needs --tag")
    parser.add_argument("--rule", default=None, help="JSON of CriticalState fields replacing DEFAULTS' (with --dims "
                        "of one dimension), e.g. '{\"rate\": 40, \"gain\": 3}'; needs --tag")
    args = parser.parse_args(argv)
    if args.dem_check:
        return dem_check(args)
    if args.shear_check:
        return shear_check(args)
    params = dict(PARAMS)
    if args.rule is not None:
        if not args.tag:
            parser.error("--rule needs --tag (the default results stay the DEFAULTS')")
        changes = json.loads(args.rule)
        params = {dim: replace(rule, **changes) for dim, rule in PARAMS.items()}
    pressures = PRESSURES
    if args.pressures is not None:
        if not args.tag:
            parser.error("--pressures needs --tag")
        pressures = tuple(float(p) for p in args.pressures.split(","))
    if args.plain:
        if not args.tag:
            parser.error("--plain needs --tag")
        params = {dim: None for dim in PARAMS}
    lines, rows = [], []

    def say(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    say(f"critical-state renewal, closed form, drained to {EPS:.0%}, increments {args.increment:g}; 2D "
        f"{args.orientations} orientations, 3D Lebedev {args.order} x {args.spins} spins; the rule's parameters: "
        f"homogenization.material.critical_state.DEFAULTS")
    for dim in (int(d) for d in args.dims.split(",")):
        say(f"\n{dim}D rule: {params[dim]}")
        say("p0        alpha0  e0     q/p end  e end   |dq/de1|/p  |dev/de1|  renewals  capped  clipped  merged  seconds")
        for p0 in pressures:
            pair = []
            for alpha0 in STATES[dim]:
                start = time.perf_counter()
                s = summary(run(dim, alpha0, p0, "drained", args, params[dim]), dim, alpha0)
                s.update(p0=p0, test="drained", seconds=time.perf_counter() - start)
                rows.append(s)
                pair.append(s)
                say(f"{p0:<9.0e} {alpha0:<7g} {s['e0']:.3f}  {s['q_over_p']:<8.3f} {s['e']:.3f}   {s['dq_rate']:<11.3f} "
                    f"{s['dv_rate']:<10.4f} {s['renewals']:<9d} {s['rate_capped']:<7d} {s['angle_clipped']:<8d} {s['merged']:<7d} "
                    f"{s['seconds']:.1f}")
            ratio = abs(pair[0]["q_over_p"] / pair[1]["q_over_p"] - 1.0)
            de = abs(pair[0]["e"] - pair[1]["e"])
            ok_rates = all(s["dq_rate"] <= 0.05 and s["dv_rate"] <= 0.01 for s in pair)
            say(f"  -> stress ratios differ by {ratio:.1%} (<= 5 %: {ratio <= 0.05}), void ratios by {de:.3f} "
                f"(<= 0.02: {de <= 0.02}), rates within 0.05 / 0.01: {ok_rates}")
        drained = [r for r in rows if r["dim"] == dim and r["test"] == "drained"]
        fit = [r for r in drained if r["p0"] in PRESSURES] or drained
        lam, e_g = np.polyfit(-np.log([r["p"] for r in fit]), [r["e"] for r in fit], 1)
        at = ", ".join(f"{p0:g}" for p0 in sorted({r["p0"] for r in fit}))
        say(f"  line through the drained ends at p0 {at}: e = {e_g:.3f} - {lam:.4f} ln p")
        for r in (r for r in drained if r not in fit):
            say(f"  drained p0 {r['p0']:g}, alpha0 {r['alpha0']:g}: end p {r['p']:.4g}, e {r['e']:.3f}; the line at "
                f"that p: e {e_g - lam * np.log(r['p']):.3f} (off by {r['e'] - e_g + lam * np.log(r['p']):+.3f})")
        near = (PARAMS[dim].alpha_c_deg - 2.0, PARAMS[dim].alpha_c_deg + 2.0)
        for alpha0 in () if args.no_undrained else STATES[dim] + near:
            start = time.perf_counter()
            s = summary(run(dim, alpha0, pressures[0], "undrained", args, params[dim]), dim, alpha0)
            s.update(p0=pressures[0], test="undrained", seconds=time.perf_counter() - start)
            rows.append(s)
            e_line = e_g - lam * np.log(s["p"])
            say(f"  undrained alpha0 {alpha0:g}: end p {s['p']:.4g}, e {s['e']:.3f}, q/p {s['q_over_p']:.3f}; the "
                f"line at that p: e {e_line:.3f} (off by {s['e'] - e_line:+.3f}); renewals {s['renewals']}, capped "
                f"{s['rate_capped']}, clipped {s['angle_clipped']}, merged {s['merged']}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"critical_state{args.tag}.txt").write_text("\n".join(lines) + "\n")
    (RESULTS / f"critical_state{args.tag}.json").write_text(json.dumps(rows, indent=1))
    figure(rows, RESULTS / f"critical_state{args.tag}.png")
    return 0


def figure(rows: list[dict], path: Path) -> None:
    """q/p and e against eps1, e against ln p, per dimension, saved to ``path``."""
    import matplotlib.pyplot as plt
    dims = sorted({r["dim"] for r in rows})
    fig, axes = plt.subplots(len(dims), 3, figsize=(13, 4 * len(dims)), squeeze=False)
    for i, dim in enumerate(dims):
        for r in (r for r in rows if r["dim"] == dim):
            c = r["curve"]
            style = "-" if r["test"] == "drained" else ":"
            label = f"{r['test']} {r['p0']:.0e}, alpha0 {r['alpha0']:g}"
            axes[i, 0].plot(c["eps1"], c["q_over_p"], style, label=label)
            axes[i, 1].plot(c["eps1"], c["e"], style, label=label)
            axes[i, 2].semilogx(c["p"], c["e"], style, label=label)
            axes[i, 2].plot(r["p"], r["e"], "ko", ms=4)
        drained = [r for r in rows if r["dim"] == dim and r["test"] == "drained"]
        drained = [r for r in drained if r["p0"] in PRESSURES] or drained
        lam, e_g = np.polyfit(-np.log([r["p"] for r in drained]), [r["e"] for r in drained], 1)
        ends = [r["p"] for r in rows if r["dim"] == dim]
        p = np.geomspace(min(ends) / 2, max(ends) * 1.5, 20)
        axes[i, 2].semilogx(p, e_g - lam * np.log(p), "k--", label="line through the drained ends")
        for ax, y in zip(axes[i], ("q/p", "e", "e")):
            ax.set_ylabel(f"{dim}D {y}")
            ax.set_xlabel("p" if ax is axes[i, 2] else "eps1")
        axes[i, 0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


if __name__ == "__main__":
    sys.exit(main())
