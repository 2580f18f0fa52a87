"""python studies/trace_real_sand_interlocking.py RESULT.json [--test cid_50kpa.csv] [--relax-strain G] [--cell-spread S] [--tag T]

Traces one Dobrany test at a result's optimum (``bench_real_sand_critical_state.py --interlocking``'s JSON), per
accepted increment of the shear: eps1, q, p, the point's void ratio e, e_c(p), the friction set for the next
increment, and over the point's cells (both planes of every ten-sphere cell, renewed cells included) the fractions
of type-1 contacts open (N1 <= 0), sliding (abs(T1) >= 0.999 mu N1 under the friction they stepped with) and
sticking, with the fraction of contacts that the friction set after the increment puts beyond its cap
(abs(T1) > mu_new N1: they must slide in the next increment), and how many of those were sticking, with their
cells' axis angles to axis 1. ``--relax-strain`` runs the lagged friction
(``Interlocking.relax_strain``), ``--cell-spread`` the cells' spread of friction (``Interlocking.cell_spread``). Output: studies/results/real_sand_interlocking_trace_TEST[_TAG].json and .txt.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand_critical_state import (INTERLOCKING, RESULTS, RULE, load, rule_values)  # noqa: E402
from bench_real_sand_spread import SETTINGS  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.interlocking import Interlocking, InterlockingFriction, critical_void_ratio  # noqa: E402
from homogenization.calibration.renewal import PopulationRenewal, laws_of  # noqa: E402
from homogenization.material.density import OPENING_RANGE_DEG, current_void_ratio, default_map, opening_angle_deg  # noqa: E402
from warp_hcell.core.dimension import dimension  # noqa: E402


def contact_fractions(cells, mu: np.ndarray) -> tuple[float, float, float]:
    """Fractions (open, sliding, sticking) of the type-1 contacts of both planes under friction ``mu`` (n_cells,)."""
    N1 = np.concatenate([cells.a.N1, cells.b.N1])
    T1 = np.concatenate([cells.a.T1, cells.b.T1])
    mu2 = np.concatenate([mu, mu])
    closed = N1 > 0.0
    slide = closed & (np.abs(T1) >= 0.999 * mu2 * N1)
    n = N1.size
    return float((~closed).sum() / n), float(slide.sum() / n), float((closed & ~slide).sum() / n)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--test", default="cid_50kpa.csv")
    parser.add_argument("--relax-strain", type=float, default=0.0)
    parser.add_argument("--cell-spread", type=float, default=0.0)
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    out = json.loads(args.result.read_text())
    opt = out["optimum"]
    names = tuple(out["rule_params"])
    coords = ("phi_g", "log10_kn", "kt_over_kn", "e_min", "e_max") + names + INTERLOCKING
    X = np.array([[opt[c] for c in coords]])
    test = load(args.test, True)
    settings = SETTINGS
    params = {"phi_g": X[:, 0], "kn": 10.0 ** X[:, 1], "kt_over_kn": X[:, 2],
              "alpha0": opening_angle_deg(test.void_ratio, X[:, 3], X[:, 4], *OPENING_RANGE_DEG[3])}
    full = forward.full_parameters(params, settings)
    points = forward.population(full, settings, test.dim)
    points.renewal = PopulationRenewal(RULE, points.material, points.state, default_map(3), full["alpha0"],
                                       laws_of(full, settings.law), settings.law, settings.radius,
                                       per_point=rule_values(names, X, len(INTERLOCKING)), e_bounds=(X[:, 3], X[:, 4]))
    m, e_gamma, lambda_c = (X[:, -3 + k] for k in range(3))
    rule = Interlocking(relax_strain=args.relax_strain, cell_spread=args.cell_spread)
    hook = InterlockingFriction(rule, points.material, points.state, full["phi_g"], np.full(1, test.void_ratio),
                                {"m": m, "e_gamma": e_gamma, "lambda_c": lambda_c}, inner=points.renewal)
    points.renewal = hook
    record = dimension(3)
    axis_deg = points.material.orient.axis_angle_deg
    rows: list[dict] = []
    shear = {"on": False}
    advance = hook.advance

    def traced(state):
        mu_before = hook.owner.mu.copy()
        new = advance(state)
        if shear["on"]:
            e = float(current_void_ratio(hook.e0, new.J)[0])
            p = float(record.mean_stress(new.stress)[0])
            opened, slide, stick = contact_fractions(new.cells, mu_before)
            N1 = np.concatenate([new.cells.a.N1, new.cells.b.N1])
            T1 = np.concatenate([new.cells.a.T1, new.cells.b.T1])
            mu_new = np.concatenate([hook.owner.mu, hook.owner.mu])
            over = (N1 > 0) & (np.abs(T1) > mu_new * N1 * 1.0000001)
            beyond = float(over.sum() / N1.size)
            was = (N1 > 0) & (np.abs(T1) >= 0.999 * np.concatenate([mu_before, mu_before]) * N1)
            pushed = np.flatnonzero(over & ~was) % hook.owner.mu.size  # sticking contacts the new cap passes
            angles = sorted(set(np.round(axis_deg[pushed % hook.n_cells], 1).tolist()))
            rows.append({"eps1": float(new.strain[0, 0] - shear["eps1_0"]), "q": float(record.deviator(new.stress)[0]),
                         "p": p, "e": e, "e_c": float(critical_void_ratio(p, e_gamma, lambda_c, rule.xi, rule.p_ref)[0]),
                         "friction_next_deg": float(hook.friction_deg[0]), "open": opened, "sliding": slide,
                         "sticking": stick, "beyond_new_cap": beyond, "pushed": int(pushed.size),
                         "pushed_axis_deg": angles})
        return new

    hook.advance = traced

    def shear_on(pts):
        shear.update(on=True, eps1_0=float(pts.state.strain[0, 0]))

    with np.errstate(all="ignore"):
        curves = forward.simulate_points(test, points, replace(settings), before_stage={1: shear_on})
    lines = [f"{args.test} at the optimum of {args.result.name} (relax_strain {args.relax_strain:g}, cell_spread {args.cell_spread:g}); e0 "
             f"{test.void_ratio:.3f}, phi_mu {opt['phi_g']:.2f}, m {float(m[0]):.3f}, e_Gamma {float(e_gamma[0]):.4f}, "
             f"lambda {float(lambda_c[0]):.4f}; contacts: type-1 of both planes, {hook.n_cells} cells",
             "eps1[%]  q[kPa]  p[kPa]  e       e_c     phi_next  open   sliding sticking beyond_new_cap  pushed (axis angles [deg])"]
    for r in rows:
        lines.append(f"{100 * r['eps1']:6.2f} {r['q'] / 1e3:7.1f} {r['p'] / 1e3:7.1f} {r['e']:.4f} {r['e_c']:.4f} "
                     f"{r['friction_next_deg']:7.2f}  {r['open']:.3f}  {r['sliding']:.3f}   {r['sticking']:.3f}    "
                     f"{r['beyond_new_cap']:.3f}  " + (f"{r['pushed']} {r['pushed_axis_deg']}" if r["pushed"] else ""))
    q = np.array([r["q"] for r in rows])
    k = int(np.argmin(np.diff(q)))
    lines.append(f"peak q {q.max() / 1e3:.1f} kPa at {100 * rows[int(np.argmax(q))]['eps1']:.2f} %; largest one-increment "
                 f"fall of q {(q[k] - q[k + 1]) / q.max():.3f} of the peak, at {100 * rows[k + 1]['eps1']:.2f} %")
    text = "\n".join(lines)
    print(text)
    stem = f"real_sand_interlocking_trace_{Path(args.test).stem}" + (f"_{args.tag}" if args.tag else "")
    (RESULTS / f"{stem}.txt").write_text(text + "\n")
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": args.result.name, "test": args.test,
                                                        "relax_strain": args.relax_strain, "cell_spread": args.cell_spread, "rows": rows,
                                                        "q_curve": curves.q[0].tolist()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
