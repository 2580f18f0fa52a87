"""python studies/bench_critical_state.py --diagnose|--scan|--fit|--long [--split 50+200|50+100] [--out FILE.json]

Why the 3D H-model's material point has no critical state on the drained triaxial tests of Dobrany sand,
and whether a small change of the ten-sphere cell gives it one. Measured at the least-squares optimum
of the linear law on each split (``studies/results/real_sand_spread_off_SPLIT.json``, the optimum
of ``bench_real_sand_spread.py --spread off``), with the calibration's forward model (Lebedev 11 x 4
aligned spins, shear increments 2e-3, isotropic 1e-3, drained Newton to 1e-5):

- ``--diagnose``: the cells along the 50 kPa test (``--p0`` another), grouped by |n . e1| (the cosine
  between the cell axis and the loading axis): their mean opening angles in both planes, the
  fraction of planes whose type-1 contacts are closed and sliding, and each group's share of sigma11
  and sigma33 at three strains;
- ``--scan``: each candidate cell below at a few values of its one parameter, the other four
  parameters held at the optimum: chi-square on the fitted tests, and per test RMS |dq| / q_peak,
  RMS d eps_v, peak q and its strain, eps_v at the end, the dilatancy d eps_v / d eps1 over the last
  five measured points;
- ``--fit CANDIDATE``: a bounded least-squares fit (scipy, finite-difference Jacobian in one batch,
  as ``hmodel calibrate --start map``'s fits) of phi_g, kn, kt/kn, alpha0 and the candidate's
  parameter on the fitted tests, from the optimum at each of ``--starts``; then the three tests
  (``--fit plain``: the four parameters, ``--starts`` the starting alpha0s);
- ``--long FILE``: the plain optimum and the ``--fit`` result of FILE (JSON) on drained tests at 50,
  100 and 200 kPa to 60 % axial strain: is q stationary, does eps_v level off?

The candidates (none is in the package; each is a subclass of the closed form's
``Analytical3DCell`` here, with one parameter per cell):

- ``reform`` [deg]: a plane of a cell whose contacts are all open re-forms touching and force-free at
  the opening angle alpha_r (its grains fall back into contact);
- ``freeze`` [deg]: a plane that starts an increment opened to alpha >= alpha_c with its type-1
  contacts closed keeps its state (its forces) while the cell is strained: a limit opening beyond
  which the cell deforms at constant forces, the grains rearranging;
- ``lock`` [deg]: a plane that starts an increment closed to alpha <= alpha_min sticks (its type-1
  contacts do not slide): a limit closing angle where lateral grains meet;
- ``renewal`` [1/strain]: every cell is replaced by a fresh touching, force-free cell at its alpha0
  each time its own accumulated distortion sum_ij |d eps_i - d eps_j| (cell axes, shear stage only)
  passes (j + phi_k) / lambda, phi_k = frac(k g) a fixed phase per cell (g the golden ratio's
  fractional part): a fraction lambda of the contact network rebuilt per unit strain;
- ``renewal-density`` [1/strain]: the same, the fresh cell at the opening angle whose touching
  volume is V(alpha0) J (J the cell's volume ratio since its start): new cells as loose as the point.

``--axisymmetric`` drives the cells (of --scan, --fit) by the kinematics of the cell kind hcell3d-axisym
(docs/model.md, section 14: both planes of a cell take the same lateral strain, and an isochoric
path strains no plane's area) instead of the projected ones of the calibration's forward model.

Counts of the rules are printed beside the results (planes under the rule at the end, renewals).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, SPLITS, print_prediction_table  # noqa: E402
from bench_real_sand_spread import NOISE, SETTINGS, metrics  # noqa: E402

from homogenization.backends.analytical import Analytical3DCell, Analytical3DState, AnalyticalState  # noqa: E402
from homogenization.calibration import bayes, forward, start  # noqa: E402
from homogenization.calibration.data import Measurement, read_test  # noqa: E402
from homogenization.element_test.points import material_points, orientation_set  # noqa: E402
from homogenization.element_test.record import History  # noqa: E402
from homogenization.element_test.stages import run_stages  # noqa: E402
from homogenization.element_test.solver import POPULATION, StressControl  # noqa: E402
from warp_hcell.mesostructures.hcell import build_h_cell_3d  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
SCAN = {"reform": (55.0, 60.0, 64.0, 68.0, 75.0), "freeze": (58.0, 60.0, 62.0, 64.0, 66.0),
        "lock": (45.0, 47.0, 50.0), "renewal": (1.0, 2.0, 3.0, 5.0, 10.0), "renewal-density": (0.5, 1.0, 2.0, 3.0)}
"""Values of each candidate's parameter in ``--scan``."""
BOUNDS = {"reform": (46.0, 85.0), "freeze": (57.0, 80.0), "lock": (40.0, 56.0), "renewal": (0.0, 5.0),
          "renewal-density": (0.0, 5.0)}
"""Bounds of each candidate's parameter in ``--fit``; the other four: the prior of bench_real_sand.py."""
LOWER = np.array([10.0, math.log10(3e6), 0.1, 45.0 + 1e-6])
UPPER = np.array([45.0, math.log10(3e8), 1.5, 85.0])


def _planes(state) -> tuple[AnalyticalState, AnalyticalState]:
    return state.a, state.b


def _where(mask: np.ndarray, a: AnalyticalState, b: AnalyticalState) -> AnalyticalState:
    return AnalyticalState(*(np.where(mask, x, y) for x, y in zip(a, b)))


class Candidate(Analytical3DCell):
    """A ten-sphere cell of the closed form with one more rule; ``value`` (n_cells,) its parameter."""

    value: np.ndarray
    shear: bool = False

    def configure(self, value: np.ndarray, cells_per_point: int) -> None:
        self.value = value

    def rule_count(self, state) -> np.ndarray:
        """Per cell, its planes under the rule in ``state`` (renewal: the renewals so far), shape (n_cells,)."""
        return np.zeros(state.a.alpha.size, dtype=np.int64)


class Reform(Candidate):
    def step(self, state, d_eps_local, *, with_tangent=False):
        new, response = super().step(state, d_eps_local, with_tangent=with_tangent)
        planes = []
        for plane in _planes(new):
            free = (plane.N1 <= 0.0) & (plane.N2 <= 0.0)
            planes.append(_where(free, self.touching_plane(self.value, free.size), plane))
        new = Analytical3DState(*planes)
        r = self.response(new)
        return new, type(response)(r.moment, r.area, response.diagnostics, response.tangent)

    def rule_count(self, state) -> np.ndarray:
        return sum(((p.N1 <= 0.0) & (p.N2 <= 0.0)).astype(np.int64) for p in _planes(state))


class Freeze(Candidate):
    def _held(self, plane: AnalyticalState) -> np.ndarray:
        return (plane.alpha >= np.radians(self.value)) & (plane.N1 > 0.0)

    def step(self, state, d_eps_local, *, with_tangent=False):
        new, response = super().step(state, d_eps_local, with_tangent=with_tangent)
        held = [self._held(p) for p in _planes(state)]
        new = Analytical3DState(*(_where(h, old, p) for h, old, p in zip(held, _planes(state), _planes(new))))
        tangent = response.tangent
        if tangent is not None:
            tangent = tangent.copy()
            tangent[held[0], 1, :] = 0.0
            tangent[held[1], 2, :] = 0.0
            tangent[held[0] & held[1], 0, :] = 0.0
        r = self.response(new)
        return new, type(response)(r.moment, r.area, response.diagnostics, tangent)

    def rule_count(self, state) -> np.ndarray:
        return sum(self._held(p).astype(np.int64) for p in _planes(state))


class Lock(Candidate):
    def step(self, state, d_eps_local, *, with_tangent=False):
        mu, limit = self.mu, np.radians(self.value)
        d_eps = np.asarray(d_eps_local, dtype=np.float64)
        planes, responses = [], []
        for plane, columns in zip(_planes(state), ([0, 1], [0, 2])):
            self.mu = np.where(plane.alpha <= limit, 1e6, mu)
            new_plane, response = self.plane_step(plane, d_eps[:, columns], with_tangent=with_tangent)
            planes.append(new_plane)
            responses.append(response)
        self.mu = mu
        new = Analytical3DState(*planes)
        ra, rb = responses
        tangent = None
        if with_tangent:
            tangent = np.zeros((d_eps.shape[0], 3, 3))
            tangent[:, 0, 0] = ra.tangent[:, 0, 0] + rb.tangent[:, 0, 0]
            tangent[:, 0, 1], tangent[:, 0, 2] = ra.tangent[:, 0, 1], rb.tangent[:, 0, 1]
            tangent[:, 1, 0], tangent[:, 1, 1] = ra.tangent[:, 1, 0], ra.tangent[:, 1, 1]
            tangent[:, 2, 0], tangent[:, 2, 2] = rb.tangent[:, 1, 0], rb.tangent[:, 1, 1]
        diagnostics = {k: ra.diagnostics[k] + rb.diagnostics[k] for k in ra.diagnostics}
        r = self.response(new)
        return new, type(ra)(r.moment, r.area, diagnostics, tangent)

    def rule_count(self, state) -> np.ndarray:
        return sum((p.alpha <= np.radians(self.value)).astype(np.int64) for p in _planes(state))


class RenewalState(NamedTuple):
    """Both planes, the accumulated distortion s [-] and the volume ratio J [-] of each cell (n_cells,)."""

    a: AnalyticalState
    b: AnalyticalState
    s: np.ndarray
    J: np.ndarray


class Renewal(Candidate):
    at_density = False

    def configure(self, value: np.ndarray, cells_per_point: int) -> None:
        self.value = value
        self.phase = np.mod(np.arange(value.size) % cells_per_point * GOLDEN, 1.0)

    def init_state(self, mesostructure, n_cells):
        state = super().init_state(mesostructure, n_cells)
        return RenewalState(state.a, state.b, np.zeros(n_cells), np.ones(n_cells))

    def _fresh(self, J: np.ndarray) -> Analytical3DState:
        alpha0 = np.broadcast_to(self.cell_alpha0_deg, J.shape)
        if self.at_density:
            grid = np.linspace(45.0 + 1e-6, 74.0, 800)  # the touching cell's volume grows up to 74.7 deg
            volume = super().volume(self.touching_state(grid, grid.size))
            alpha0 = np.interp(np.interp(alpha0, grid, volume) * J, volume, grid)
        return self.touching_state(alpha0, J.size)

    def step(self, state, d_eps_local, *, with_tangent=False):
        new, response = super().step(Analytical3DState(state.a, state.b), d_eps_local, with_tangent=with_tangent)
        d = np.asarray(d_eps_local, dtype=np.float64)
        J = state.J * (1.0 - d[:, 0]) * (1.0 - d[:, 1]) * (1.0 - d[:, 2])
        distortion = np.abs(d[:, 0] - d[:, 1]) + np.abs(d[:, 0] - d[:, 2]) + np.abs(d[:, 1] - d[:, 2])
        s = state.s + (distortion if self.shear else 0.0)
        renew = self._renewals(s) > self._renewals(state.s)
        if renew.any():
            fresh = self._fresh(J)
            new = Analytical3DState(_where(renew, fresh.a, new.a), _where(renew, fresh.b, new.b))
            r = super().response(new)
            response = type(response)(r.moment, r.area, response.diagnostics, response.tangent)
        return RenewalState(new.a, new.b, s, J), response

    def _renewals(self, s: np.ndarray) -> np.ndarray:
        return np.floor(self.value * s + self.phase)

    def response(self, state):
        return super().response(Analytical3DState(state.a, state.b))

    def volume(self, state):
        return super().volume(Analytical3DState(state.a, state.b))

    def state_to_arrays(self, state):
        return {**super().state_to_arrays(Analytical3DState(state.a, state.b)), "s": state.s, "J": state.J}

    def state_from_arrays(self, arrays):
        arrays = dict(arrays)
        s, J = arrays.pop("s"), arrays.pop("J")
        state = super().state_from_arrays(arrays)
        return RenewalState(state.a, state.b, s, J)

    def rule_count(self, state) -> np.ndarray:
        return (self._renewals(state.s) - self._renewals(np.zeros_like(state.s))).astype(np.int64)


class RenewalAtDensity(Renewal):
    at_density = True


CANDIDATES = {"reform": Reform, "freeze": Freeze, "lock": Lock, "renewal": Renewal, "renewal-density": RenewalAtDensity}


AXISYMMETRIC = False
"""``--axisymmetric``: drive the cells by the axisymmetric kinematics of the cell kind hcell3d-axisym."""


def simulate(test: Measurement, params: dict[str, np.ndarray], candidate: str | None, values: np.ndarray | None):
    """The forward model's drained test (``forward.simulate``'s batched path) of n parameter sets, the
    cells of set i those of ``candidate`` with parameter values[i] (None: the plain closed form), driven
    by the kinematics of hcell3d-axisym where ``AXISYMMETRIC``.
    Returns the curves and, per set, the rule's count at the end."""
    full = forward.full_parameters(params, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    if AXISYMMETRIC:
        meso = build_h_cell_3d(57.0, radius=SETTINGS.radius, axisymmetric=True)
        orient = orientation_set(meso, n_orientations=SETTINGS.n_orientations, lebedev_order=SETTINGS.lebedev_order,
                                 n_spins=SETTINGS.n_spins, staggered_spins=SETTINGS.staggered_spins)
        points = material_points(points.model, meso, points.n, orient)
    model = points.model
    before = {}
    if candidate is not None:
        cells = points.material.orient.n_cells
        model.__class__ = CANDIDATES[candidate]  # the same cells with the candidate's rule
        model.configure(np.repeat(np.asarray(values, dtype=np.float64), cells), cells)
        points.state = points.material.init_state()

        def start_shear(_points) -> None:
            model.shear = True

        before = {1: start_shear}
    curves = forward.simulate_points(test, points, SETTINGS, before_stage=before)
    counts = np.zeros(points.n, dtype=np.int64)
    if candidate is not None:
        counts = model.rule_count(points.state.cells).reshape(points.n, -1).sum(axis=1)
    return curves, counts


def optimum(split: str) -> dict[str, float]:
    return json.loads((RESULTS / f"real_sand_spread_off_{split.replace('+', '_')}.json").read_text())["optimum"]


def row(test: Measurement, curves: forward.Curves, i: int) -> dict[str, float]:
    """``metrics`` of set i, with q at the end, the late dilatancy and the fallbacks."""
    e, ev = test.eps1, curves.eps_v[i]
    return {**metrics(test, curves.q[i], ev), "q_end": float(curves.q[i, -1]),
            "dilatancy_end": float((ev[-1] - ev[-6]) / (e[-1] - e[-6])), "forward_fallbacks": int(curves.n_fallback[i])}


def all_tests(split: str, params: dict[str, np.ndarray], candidate: str | None, values) -> tuple[np.ndarray, dict]:
    """Chi-square on the split's fitted tests and the rows of all three tests, per set."""
    fitted, predicted = SPLITS[split]
    n = len(next(iter(params.values())))
    chi2, out = np.zeros(n), {}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = read_test(DATA / name)
        with np.errstate(all="ignore"):
            curves, counts = simulate(test, params, candidate, values)
        if name in fitted:
            chi2 += np.sum(bayes.residuals([test], [{"q": curves.q, "p": curves.p, "eps_v": curves.eps_v}], NOISE) ** 2,
                           axis=1)
        out[name] = [{"role": "predicted" if name == predicted else "fitted", **row(test, curves, i),
                      "rule_count": int(counts[i])} for i in range(n)]
    return chi2, out


def print_rows(label: str, chi2: float, rows: dict, i: int) -> None:
    print(f"{label}: chi-square fitted {chi2:.4g}")
    for name, r in rows.items():
        m = r[i]
        print(f"   {name:15s} {m['role']:9s} {m['rms_dq_over_qpeak']:.3f}  {100 * m['rms_deps_v']:5.2f} %  "
              f"q_pk {m['q_peak_model'] / 1e3:4.0f}/{m['q_peak_data'] / 1e3:.0f}  at {100 * m['eps1_at_peak_model']:4.1f}/"
              f"{100 * m['eps1_at_peak_data']:.1f} %  eps_v end {100 * m['eps_v_end_model']:6.1f}/{100 * m['eps_v_end_data']:.1f} %  "
              f"q end {m['q_end'] / 1e3:4.0f}  d eps_v/d eps1 end {m['dilatancy_end']:+.2f}  "
              f"rule {m['rule_count']}  fallbacks {m['forward_fallbacks']}")


def scan(args) -> dict:
    base = optimum(args.split)
    print(f"split {args.split}, at the linear optimum " + ", ".join(f"{k} {v:.4g}" for k, v in base.items()))
    print("   test            role      RMS|dq|/q_pk  RMS d eps_v  peak q model/data [kPa] at eps1 [%] ...")
    chi2, rows = all_tests(args.split, {k: np.array([v]) for k, v in base.items()}, None, None)
    print_rows("plain cell", chi2[0], rows, 0)
    out = {"split": args.split, "at": base, "plain": {"chi_square_fitted": float(chi2[0]), "tests": rows}, "candidates": {}}
    for name in args.candidates:
        values = np.array(SCAN[name])
        chi2, rows = all_tests(args.split, {k: np.full(values.size, v) for k, v in base.items()}, name, values)
        out["candidates"][name] = {"values": values.tolist(), "chi_square_fitted": chi2.tolist(), "tests": rows}
        for i, v in enumerate(values):
            print_rows(f"{name} {v:g}", chi2[i], rows, i)
    return out


def fit(args) -> dict:
    fitted, _ = SPLITS[args.split]
    tests = [read_test(DATA / f) for f in fitted]
    base = optimum(args.split)
    rule = args.fit if args.fit != "plain" else None
    lo, hi = (np.append(LOWER, BOUNDS[rule][0]), np.append(UPPER, BOUNDS[rule][1])) if rule else (LOWER, UPPER)
    evaluations = [0]

    def residuals(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        params = {"phi_g": X[:, 0], "kn": 10.0 ** X[:, 1], "kt_over_kn": X[:, 2], "alpha0": X[:, 3]}
        curves = []
        for test in tests:
            with np.errstate(all="ignore"):
                c, _ = simulate(test, params, rule, X[:, 4] if rule else None)
            curves.append({"q": c.q, "p": c.p, "eps_v": c.eps_v})
        evaluations[0] += X.shape[0]
        r = bayes.residuals(tests, curves, NOISE)
        return np.where(np.isfinite(r), r, 1e3)

    started = time.perf_counter()
    fits = []
    for value in args.starts:
        x0 = np.array([base["phi_g"], math.log10(base["kn"]), base["kt_over_kn"], base["alpha0"]])
        if rule:
            x0 = np.append(x0, value)
        else:
            x0[3] = value
        chi_square, result = start.least_squares_fit(residuals, np.clip(x0, lo, hi), lo, hi)
        fits.append({"start": value, "chi_square": chi_square, "x": result.x.tolist()})
        x = result.x
        print(f"fit from {args.fit} {value:g}: chi-square {2.0 * result.cost:.4g} at phi_g {x[0]:.2f}, kn {10 ** x[1]:.3g}, "
              f"kt/kn {x[2]:.3f}, alpha0 {x[3]:.2f}" + (f", {args.fit} {x[4]:.3f}" if rule else "")
              + f" ({result.nfev} iterations)", flush=True)
    best = min(fits, key=lambda f: f["chi_square"])
    x = np.array(best["x"])
    params = {"phi_g": x[0], "kn": 10.0 ** x[1], "kt_over_kn": x[2], "alpha0": x[3]}
    chi2, rows = all_tests(args.split, {k: np.array([v]) for k, v in params.items()}, rule,
                           np.array([x[4]]) if rule else None)
    seconds = time.perf_counter() - started
    print(f"split {args.split}, {args.fit}{' (axisymmetric kinematics)' if AXISYMMETRIC else ''}: optimum "
          + ", ".join(f"{k} {v:.4g}" for k, v in params.items())
          + (f", {args.fit} {x[4]:.4g}" if rule else "") + f"; chi-square {chi2[0]:.4g} ({evaluations[0]} sets, {seconds:.0f} s, "
          f"load {os.getloadavg()[0]:.1f})")
    print_prediction_table({k: v[0] for k, v in rows.items()}, fallbacks=True)
    print("rule counts (" + args.fit + "): " + ", ".join(f"{k} {v[0]['rule_count']}" for k, v in rows.items()))
    return {"split": args.split, "candidate": args.fit, "axisymmetric": AXISYMMETRIC,
            "optimum": {**{k: float(v) for k, v in params.items()}, **({args.fit: float(x[4])} if rule else {})},
            "chi_square_fitted": float(chi2[0]), "fits": fits, "tests": {k: v[0] for k, v in rows.items()},
            "evaluations": evaluations[0], "seconds": seconds, "load_average_at_end": list(os.getloadavg())}


LONG_EPS = np.arange(0.02, 0.6001, 0.02)
"""Axial strains of ``--long`` [-]."""


def long_run(args) -> dict:
    result = json.loads(args.long.read_text())
    split, name, best = result["split"], result["candidate"], dict(result["optimum"])
    value = best.pop(name)
    out = {"from": str(args.long), "rows": []}
    template = read_test(DATA / "cid_50kpa.csv")
    for p0 in (5e4, 1e5, 2e5):
        test = replace(template, p0=p0, eps1=LONG_EPS, observed={})
        for label, params, candidate, values in (
                ("plain", optimum(split), None, None), (f"{name} {value:.3g}", best, name, np.array([value]))):
            with np.errstate(all="ignore"):
                c, counts = simulate(test, {k: np.array([v]) for k, v in params.items()}, candidate, values)
            q, ev = c.q[0], c.eps_v[0]
            late = (ev[-1] - ev[19]) / (LONG_EPS[-1] - LONG_EPS[19])
            out["rows"].append({"p0": p0, "cell": label, "eps1": LONG_EPS[4::5].tolist(), "q": q[4::5].tolist(),
                                "eps_v": ev[4::5].tolist(), "dilatancy_40_60": float(late),
                                "q_60_over_40": float(q[-1] / q[19]), "rule_count": int(counts[0]),
                                "forward_fallbacks": int(c.n_fallback[0])})
            print(f"{p0 / 1e3:3.0f} kPa {label:15s} eps1 [%]: q [kPa] / eps_v [%]: "
                  + "  ".join(f"{100 * e:.0f}: {qq / 1e3:.0f} / {100 * v:.1f}" for e, qq, v in zip(LONG_EPS[4::5], q[4::5], ev[4::5]))
                  + f"  | d eps_v/d eps1 40-60 %: {late:+.3f}, q(60 %)/q(40 %): {q[-1] / q[19]:.2f}, "
                  f"rule {counts[0]}, fallbacks {c.n_fallback[0]}")
    return out


def diagnose(args) -> dict:
    base = optimum(args.split)
    test = replace(read_test(DATA / "cid_50kpa.csv"), p0=args.p0)
    full = forward.full_parameters({k: np.array([v]) for k, v in base.items()}, SETTINGS)
    points = forward.population(full, SETTINGS, 3)
    stages = forward.stages(test, SETTINGS, points)
    frames, weights = points.material.orient.frames, points.material.orient.weights
    group = np.round(np.abs(frames[:, 0, 0]), 2)
    groups = np.unique(group)
    mu = math.tan(math.radians(base["phi_g"]))
    records = []

    class Recorder:
        def __init__(self, plan):
            self.plan = plan

        def __enter__(self):
            return self.record

        def __exit__(self, *exc):
            return False

        def record(self, plan, pts):
            if plan.label != "shear":
                return
            cells = pts.state.cells
            moment = points.model.response(cells).moment
            sigma = np.einsum("k,kij,kj,klj->kil", weights, frames, np.diagonal(moment, axis1=1, axis2=2), frames)
            records.append({"eps": pts.state.strain[0, :3].copy(), "sigma": pts.state.stress[0, :3].copy(),
                            "alpha": [np.degrees(p.alpha) for p in _planes(cells)],
                            "closed": [p.N1 > 0.0 for p in _planes(cells)],
                            "sliding": [(p.N1 > 0.0) & (np.abs(p.T1) >= mu * p.N1 * (1.0 - 1e-9)) for p in _planes(cells)],
                            "share": np.array([[sigma[group == g, i, i].sum() / sigma[:, i, i].sum() for i in (0, 2)]
                                               for g in groups])})

    solver = StressControl(points, replace(POPULATION, rtol=SETTINGS.stress_rtol, max_iterations=SETTINGS.max_newton))
    run_stages(solver, stages, History(sum(p.n_increments for p in stages), 1, 3, observe=False), progress=Recorder)
    print(f"{args.p0 / 1e3:.0f} kPa at the {args.split} optimum; groups of |n . e1| (cells, weight): "
          + ", ".join(f"{g:.2f} ({np.count_nonzero(group == g)}, {weights[group == g].sum():.3f})" for g in groups))
    print("eps1 [%]  q [kPa]  eps_v [%]  | per group: alpha plane A / B [deg], type-1 closed, sliding (fraction of planes)")
    table = []
    for k in list(range(4, len(records), 10)):
        r = records[k]
        e, s = r["eps"], r["sigma"]
        cells = []
        for g in groups:
            m = group == g
            closed = np.mean(np.concatenate([c[m] for c in r["closed"]]))
            sliding = np.mean(np.concatenate([c[m] for c in r["sliding"]]))
            cells.append({"group": float(g), "alpha_a": float(r["alpha"][0][m].mean()), "alpha_b": float(r["alpha"][1][m].mean()),
                          "closed": float(closed), "sliding": float(sliding)})
        table.append({"eps1": float(e[0]), "q": float(s[0] - s[2]), "eps_v": float(e.sum()), "groups": cells,
                      "share_sigma11_sigma33": r["share"].tolist()})
        print(f"{100 * e[0]:6.1f} {(s[0] - s[2]) / 1e3:8.1f} {100 * e.sum():8.2f}   | " + "  ".join(
            f"{c['group']:.2f}: {c['alpha_a']:.1f}/{c['alpha_b']:.1f} {c['closed']:.2f} {c['sliding']:.2f}" for c in cells))
    for k in (len(records) // 4, len(records) // 2, len(records) - 1):
        r = records[k]
        print(f"share of sigma11 / sigma33 by group at eps1 = {100 * r['eps'][0]:.1f} %: "
              + ", ".join(f"{g:.2f}: {a:.2f} / {b:.2f}" for g, (a, b) in zip(groups, r["share"])))
    return {"split": args.split, "at": base, "p0": args.p0, "table": table}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--diagnose", action="store_true")
    mode.add_argument("--scan", action="store_true")
    mode.add_argument("--fit", choices=("plain", *CANDIDATES))
    mode.add_argument("--long", type=Path, help="a --fit result (JSON)")
    parser.add_argument("--split", choices=tuple(SPLITS), default="50+200")
    parser.add_argument("--p0", type=float, default=5e4, help="--diagnose: confining pressure [Pa]")
    parser.add_argument("--candidates", default=",".join(CANDIDATES), help="--scan: which candidates (comma-separated)")
    parser.add_argument("--starts", default="1.5", help="--fit: starting values of the candidate's parameter "
                                                           "(--fit plain: of alpha0 [deg])")
    parser.add_argument("--axisymmetric", action="store_true",
                        help="--scan, --fit: the cells driven by the kinematics of hcell3d-axisym (model page, section 14)")
    parser.add_argument("--out", type=Path, default=None, help="result JSON")
    args = parser.parse_args(argv)
    global AXISYMMETRIC
    AXISYMMETRIC = args.axisymmetric
    args.candidates = [c for c in args.candidates.split(",") if c]
    if any(c not in CANDIDATES for c in args.candidates):
        parser.error(f"--candidates: one of {', '.join(CANDIDATES)}")
    try:
        args.starts = [float(v) for v in args.starts.split(",")]
    except ValueError:
        parser.error(f"--starts {args.starts!r}: comma-separated numbers")
    if args.long is not None and not args.long.is_file():
        parser.error(f"--long {args.long}: no such file")
    started = time.perf_counter()
    out = diagnose(args) if args.diagnose else scan(args) if args.scan else fit(args) if args.fit else long_run(args)
    out["seconds"] = out.get("seconds", time.perf_counter() - started)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
