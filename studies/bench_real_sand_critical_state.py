"""python studies/bench_real_sand_critical_state.py --split 50+200|50+100 [--kinematics K] [--rule-params NAMES]
                                                  [--starts A,B] [--max-nfev N] [--plain] [--tag T]

Dobrany sand with the critical-state renewal (``homogenization.material.critical_state``, ``DEFAULTS[3]``):
fitted on two drained triaxial tests, the third predicted. A bounded least-squares fit (``hmodel calibrate
--start map``'s: ``calibration.start.least_squares_fit``, finite-difference Jacobian in one batch, noise 2 % of
each channel's largest value, q and eps_v) of phi_g, log10 kn, kt/kn, alpha0 and the rule's parameters named
by ``--rule-params`` (default alpha_c_deg; also rate, as log10, gain, rate_gain), the others at ``DEFAULTS[3]``,
on the calibration's forward model (``calibration.forward.simulate`` with ``ForwardSettings.critical_state``:
Lebedev 11 x 4 aligned spins, shear increments 2e-3, isotropic 1e-3, drained Newton to 1e-5; void-ratio map
the default one). ``--kinematics amplified`` drives the cells as the cell kind hcell3d-sand does, ``axisymmetric``
as hcell3d-axisym. ``--starts``: alpha0 of each start (the others: ``START``). ``--start NAME=VALUE,...`` moves the start's other coordinates. ``--void-ratio`` runs each test at its specimen's void ratio (``specimens.json``) on the map and fits e_min,
e_max instead of alpha0 (each set renews on its own map). ``--plain`` fits the plain cell
(no renewal) with the same settings, for comparison. Then all three tests at the optimum: RMS abs(dq) / q_peak,
RMS d eps_v, peak q and its strain, eps_v at the end, late dilatancy, fallbacks, renewals.

``--interlocking`` adds the interlocking friction (``calibration.interlocking``: tan phi = (e_c(p) / e)^m tan phi_g,
e_c(p) = e_Gamma - lambda (p / p_ref)^0.7) and fits m, e_Gamma, lambda (``INTERLOCKING``) after the rule's
parameters; ``--free-xi`` also xi (``XI``, per set); with ``--cell-spread`` also the cells' spread of friction s (``Interlocking.cell_spread``, last); ``--psi`` (with ``--void-ratio``) puts the map on the state parameter (``PSI``); ``--law hertz-mindlin`` the Hertz-Mindlin contact law (``HERTZ``); ``--kn-exponent N`` the linear law's kn of each test
times (p0 / p_ref)^N (``--fit-kn-exponent``: N fitted, from --kn-exponent); ``--orders L,S`` another Lebedev order and spin count (cheap scouting); ``--peak-sigma S`` adds each fitted
test's smoothed strain at peak (``soft_peak_strain``) to the residuals, sigma S.

``--max-nfev 0`` evaluates the start (no fit); ``--max-seconds T`` stops each fit after T s of wall time at the lowest chi-square set it has run (each new lowest goes to stderr); ``--fd-step F`` the Jacobian's step, F of each bound's width. ``--increment`` refines the shear increment (isotropic: the smaller of it and 1e-3). ``--figure FILE.json`` redraws a result's figure. Output: studies/results/real_sand_critical_state_SPLIT[_TAG].json and .png (q and eps_v against eps1,
data and model); the printout is the .txt when run through tee.
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, SPLITS, print_prediction_table  # noqa: E402
from bench_real_sand_spread import NOISE, SETTINGS, metrics  # noqa: E402

from homogenization.calibration import bayes, forward, start  # noqa: E402
from homogenization.calibration.data import Measurement, read_test  # noqa: E402
from homogenization.calibration.interlocking import Interlocking, InterlockingFriction  # noqa: E402
from homogenization.calibration.renewal import PopulationRenewal, laws_of  # noqa: E402
from homogenization.material.critical_state import DEFAULTS  # noqa: E402
from homogenization.material.density import OPENING_RANGE_DEG, default_map, opening_angle_deg  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RULE = DEFAULTS[3]
LAW = ("phi_g", "log10_kn", "kt_over_kn", "alpha0")
LAW_VOID = ("phi_g", "log10_kn", "kt_over_kn", "e_min", "e_max")
"""The fitted coordinates with ``--void-ratio``: each test's alpha0 from its specimen's void ratio on the map."""
HERTZ = ("log10_shear_modulus", "poisson")
"""With ``--law hertz-mindlin``: the law's coordinates in place of log10 kn and kt/kn (grain G [Pa] as log10, nu)."""
BOUNDS = {"phi_g": (10.0, 45.0), "log10_kn": (math.log10(3e6), math.log10(3e8)), "kt_over_kn": (0.1, 1.5),
          "alpha0": (45.0 + 1e-6, 70.0), "e_min": (0.2, 0.52), "e_max": (0.59, 1.2), "alpha_c_deg": (RULE.alpha_min_deg, RULE.alpha_max_deg),
          "log10_rate": (0.0, math.log10(RULE.rate_max)), "gain": (0.0, 8.0), "rate_gain": (0.0, 4.0),
          "interlocking_m": (0.0, 6.0), "e_gamma": (0.5, 1.2), "lambda_c": (0.0, 0.4),
          "lambda_psi": (0.0, 0.2), "cell_spread": (0.0, 0.6), "xi_c": (0.2, 1.0),
          "log10_shear_modulus": (7.0, 10.5), "poisson": (0.0, 0.45),
          "kn_exponent": (0.0, 1.0)}
"""Bounds of the fitted coordinates (the law's: the prior of bench_real_sand.py, alpha0 to 70 deg)."""
START = {"e_min": 0.45, "e_max": 0.75, "phi_g": 35.0, "log10_kn": math.log10(2e7), "kt_over_kn": 1.0, "alpha0": 50.0,
         "alpha_c_deg": RULE.alpha_c_deg, "log10_rate": math.log10(RULE.rate), "gain": RULE.gain,
         "rate_gain": RULE.rate_gain, "interlocking_m": 1.0, "e_gamma": 0.75, "lambda_c": 0.05,
         "lambda_psi": 0.0, "cell_spread": 0.0, "xi_c": Interlocking().xi,
         "log10_shear_modulus": 9.0, "poisson": 0.2, "kn_exponent": 0.0}
"""Start of every fit (alpha0 from ``--starts``)."""
PSI = ("lambda_psi",)
"""The fitted coordinate of ``--psi`` (last): each test's void ratio enters the map (and the renewal) as
e + lambda_psi (p0 / p_ref)^0.7, i.e. the map reads the state parameter psi = e - e_c(p0) up to a constant
(e_c(p) = e_Gamma - lambda_psi (p / p_ref)^0.7, e_Gamma absorbed by the map's e_min and e_max)."""
INTERLOCKING = ("interlocking_m", "e_gamma", "lambda_c")
"""The fitted coordinates of ``--interlocking`` (after the rule's): m, e_Gamma and lambda of
``calibration.interlocking``, xi fixed at ``Interlocking().xi``, phi_g its phi_mu."""
XI = ("xi_c",)
"""The fitted coordinate of ``--free-xi`` (with ``--interlocking``, after ``INTERLOCKING``): the line's xi per set."""
KN_EXPONENT = ("kn_exponent",)
"""The fitted coordinate of ``--fit-kn-exponent`` (last): n of the linear law's kn (p0 / p_ref)^n."""
PEAK_SHARPNESS = 50.0
"""``soft_peak_strain``'s sharpness: a point 2 % of q below the peak weighs 1/e of it."""
SPREAD = ("cell_spread",)
"""The fitted coordinate of ``--cell-spread`` (with ``--interlocking``, last): ``Interlocking.cell_spread``."""


def rule_values(names: tuple[str, ...], X: np.ndarray, tail: int = 0) -> dict[str, np.ndarray]:
    """The rule's per-set parameters (CriticalState field names) of coordinates X (n, law + len(names) + tail)."""
    out = {}
    for j, name in enumerate(names):
        value = X[:, X.shape[1] - tail - len(names) + j]
        out["rate" if name == "log10_rate" else name] = 10.0 ** value if name == "log10_rate" else value
    return out


def simulate(test: Measurement, X: np.ndarray, names: tuple[str, ...], settings: forward.ForwardSettings,
             plain: bool, interlocking: bool = False, stats: dict | None = None,
             psi: bool = False, spread: bool = False, xi: bool = False,
             kn_exponent: float = 0.0) -> tuple[forward.Curves, np.ndarray]:
    """Curves of ``test`` for the sets X (module docstring) and the renewals per set (0 where ``plain``);
    ``interlocking``: X's columns after the rule's are ``INTERLOCKING``'s (``stats`` gets the friction at the start
    of shear and at the end, and the clipped e_c, per set); ``psi``: X's last column is ``PSI``'s; ``spread``: X's last
    column is ``SPREAD``'s (with ``interlocking``); ``xi``: ``XI``'s column follows ``INTERLOCKING``'s; ``kn_exponent``
    n: the linear law's kn of the test is kn (p0 / p_ref)^n (p_ref 101.325 kPa)."""
    if settings.law == "hertz-mindlin":
        params = {"phi_g": X[:, 0], "shear_modulus": 10.0 ** X[:, 1], "poisson": X[:, 2], "alpha0": X[:, 3]}
    else:
        kn = 10.0 ** X[:, 1] * (test.p0 / Interlocking().p_ref) ** kn_exponent
        params = {"phi_g": X[:, 0], "kn": kn, "kt_over_kn": X[:, 2], "alpha0": X[:, 3]}
    e_bounds = None
    if test.void_ratio is not None:  # --void-ratio: X[:, 3:5] are e_min, e_max
        e_bounds = (X[:, 3], X[:, 4])
        shift = X[:, -1] * (test.p0 / Interlocking().p_ref) ** Interlocking().xi if psi else 0.0
        params["alpha0"] = opening_angle_deg(test.void_ratio + shift, *e_bounds, *OPENING_RANGE_DEG[3])
    if interlocking or psi:
        return _simulate_interlocking(test, X, names, settings, plain, params, e_bounds, stats, interlocking, psi,
                                      spread, xi)
    if plain or not names:
        s = replace(settings, critical_state=None if plain else RULE)
        if e_bounds is not None:  # forward.simulate maps the void ratio itself
            params = {**{k: v for k, v in params.items() if k != "alpha0"}, "e_min": e_bounds[0], "e_max": e_bounds[1]}
        with np.errstate(all="ignore"):
            curves = forward.simulate(test, params, s)
        return curves, np.zeros(X.shape[0], dtype=np.int64)
    full = forward.full_parameters(params, settings)
    points = forward.population(full, settings, test.dim)
    points.renewal = PopulationRenewal(RULE, points.material, points.state, default_map(3), full["alpha0"],
                                       laws_of(full, settings.law), settings.law, settings.radius,
                                       per_point=rule_values(names, X), e_bounds=e_bounds)
    with np.errstate(all="ignore"):
        curves = forward.simulate_points(test, points, settings)
    return curves, np.asarray(points.renewal.count)


def _simulate_interlocking(test, X, names, settings, plain, params, e_bounds, stats, interlocking=True, psi=False,
                           spread=False, xi=False):
    """``simulate`` with the interlocking friction on top of the renewal (or of the plain cell), and/or with the
    map on the state parameter (``psi``: sets whose map misses the shifted void ratio get NaN curves)."""
    missed = ~np.isfinite(params["alpha0"])
    params = {**params, "alpha0": np.where(missed, 50.0, params["alpha0"])}
    full = forward.full_parameters(params, settings)
    points = forward.population(full, settings, test.dim)
    tail = (len(INTERLOCKING) + xi) * interlocking + psi + spread
    if not plain:
        points.renewal = PopulationRenewal(RULE, points.material, points.state, default_map(3), full["alpha0"],
                                           laws_of(full, settings.law), settings.law, settings.radius,
                                           per_point=rule_values(names, X, tail) or None, e_bounds=e_bounds)
    hook = None
    if interlocking:
        if test.void_ratio is not None:
            e0 = np.full(X.shape[0], test.void_ratio)
        else:
            e0 = np.array([default_map(3).void_ratio(a) for a in full["alpha0"]])
        cols = X[:, X.shape[1] - tail:X.shape[1] - tail + len(INTERLOCKING)]
        per_point = {"m": cols[:, 0], "e_gamma": cols[:, 1], "lambda_c": cols[:, 2]}
        if xi:
            per_point["xi"] = X[:, X.shape[1] - tail + len(INTERLOCKING)]
        if spread:
            per_point["cell_spread"] = X[:, -1]
        hook = InterlockingFriction(Interlocking(), points.material, points.state, full["phi_g"], e0, per_point,
                                    inner=points.renewal)
        points.renewal = hook
    at_shear = {}
    with np.errstate(all="ignore"):
        curves = forward.simulate_points(test, points, settings, before_stage=None if hook is None else {
            1: lambda pts: at_shear.update(phi=hook.friction_deg.copy())})
    for name in ("q", "p", "eps_v"):
        curves.channel(name)[missed] = np.nan
    if stats is not None and hook is not None:
        stats.update(friction_shear_start=at_shear.get("phi"), friction_end=hook.friction_deg.copy(),
                     floored=hook.floored.copy(), fallbacks=hook.fallbacks.copy())
    count = points.renewal.count if points.renewal is not None else np.zeros(X.shape[0], dtype=np.int64)
    return curves, np.asarray(count)


def load(name: str, void_ratio: bool) -> Measurement:
    """The test of file ``name``, with its specimen's void ratio at the start of shear where ``void_ratio``."""
    test = read_test(DATA / name)
    if not void_ratio:
        return test
    specimens = json.loads((DATA / "specimens.json").read_text())["tests"]
    return replace(test, void_ratio=float(next(t for t in specimens if t.get("file") == name)["void_ratio_start_of_shear"]))


def row(test: Measurement, curves: forward.Curves, i: int, renewals: int) -> dict[str, float]:
    e, ev = test.eps1, curves.eps_v[i]
    return {**metrics(test, curves.q[i], ev), "q_end": float(curves.q[i, -1]),
            "dilatancy_end": float((ev[-1] - ev[-6]) / (e[-1] - e[-6])), "forward_fallbacks": int(curves.n_fallback[i]),
            "renewals": int(renewals)}


def soft_peak_strain(eps1: np.ndarray, q: np.ndarray, sharpness: float = PEAK_SHARPNESS) -> np.ndarray:
    """Strain at peak of curves q (n_sets, n_points) at eps1 (n_points,), smoothed: the mean of eps1 weighted by
    exp(sharpness (q / q_max - 1)), so points within 1 / sharpness of the peak count (a ragged plateau's
    centre instead of its highest point; a finite-difference Jacobian can see it). Returns (n_sets,), NaN
    for a curve without a finite point."""
    q = np.atleast_2d(q)
    with np.errstate(all="ignore"):
        w = np.exp(sharpness * (q / np.nanmax(q, axis=1, keepdims=True) - 1.0))
        w = np.where(np.isfinite(w), w, 0.0)
        return np.sum(w * eps1, axis=1) / np.sum(w, axis=1)


class _OutOfTime(Exception):
    """A fit ran past ``--max-seconds``."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=tuple(SPLITS))
    parser.add_argument("--figure", type=Path, help="redraw the figure of a result JSON and stop")
    parser.add_argument("--kinematics", default="projected", choices=("projected", "amplified", "axisymmetric"))
    parser.add_argument("--rule-params", default="alpha_c_deg")
    parser.add_argument("--starts", default="50")
    parser.add_argument("--start", default="", help="NAME=VALUE,... overriding START")
    parser.add_argument("--max-nfev", type=int, default=30)
    parser.add_argument("--plain", action="store_true")
    parser.add_argument("--increment", type=float, default=SETTINGS.increment, help="shear increment [-]")
    parser.add_argument("--void-ratio", action="store_true",
                        help="each test at its specimen's void ratio on the map; fit e_min, e_max instead of alpha0")
    parser.add_argument("--interlocking", action="store_true",
                        help="fit the interlocking friction's m, e_gamma, lambda_c too (calibration.interlocking)")
    parser.add_argument("--cell-spread", action="store_true",
                        help="with --interlocking: fit the cells' spread of friction too (Interlocking.cell_spread)")
    parser.add_argument("--law", default="linear", choices=("linear", "hertz-mindlin"),
                        help="the contact law; hertz-mindlin fits log10 G and nu in place of log10 kn and kt/kn")
    parser.add_argument("--kn-exponent", type=float, default=0.0,
                        help="linear law: each test's kn is kn (p0 / p_ref)^N (N = 1/3: Hertz's tangent stiffness)")
    parser.add_argument("--fit-kn-exponent", action="store_true",
                        help="fit that exponent too (KN_EXPONENT, last coordinate; --kn-exponent: its start)")
    parser.add_argument("--free-xi", action="store_true",
                        help="with --interlocking: fit the line's exponent xi too (XI, per set)")
    parser.add_argument("--psi", action="store_true",
                        help="with --void-ratio: the map on the state parameter, lambda_psi fitted (PSI)")
    parser.add_argument("--orders", default="", help="LEBEDEV,SPINS: a cheaper or finer orientation rule")
    parser.add_argument("--max-seconds", type=float, default=0.0,
                        help="stop each fit after this wall time [s] at the lowest chi-square set it has run (0: none)")
    parser.add_argument("--fd-step", type=float, default=0.0,
                        help="the Jacobian's forward-difference step as a fraction of each bound's width (0: MAP_STEP)")
    parser.add_argument("--peak-sigma", type=float, default=0.0,
                        help="add each fitted test's smoothed strain at peak (soft_peak_strain, model against data) "
                             "to the residuals with this sigma [strain] (0: not)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    if args.figure:
        figure(json.loads(args.figure.read_text()), args.figure.with_suffix(".png"))
        return 0
    if args.split is None:
        parser.error("--split is required")
    names = tuple(n for n in args.rule_params.split(",") if n) if not args.plain else ()
    for name in names:
        if name not in BOUNDS or name in LAW or name in INTERLOCKING or name in PSI or name in XI + SPREAD:
            print(f"--rule-params: {name!r} is not one of alpha_c_deg, log10_rate, gain, rate_gain", file=sys.stderr)
            return 2
    settings = replace(SETTINGS, kinematics=args.kinematics, increment=args.increment, law=args.law,
                       iso_increment=min(SETTINGS.iso_increment, args.increment))
    if args.orders:
        order, spins = (int(v) for v in args.orders.split(","))
        settings = replace(settings, lebedev_order=order, n_spins=spins)
    fitted, predicted = SPLITS[args.split]
    tests = [load(f, args.void_ratio) for f in fitted]
    law = LAW_VOID if args.void_ratio else LAW
    if args.law == "hertz-mindlin":
        law = law[:1] + HERTZ + law[3:]
    if args.psi and not args.void_ratio:
        parser.error("--psi needs --void-ratio")
    if args.cell_spread and (not args.interlocking or args.psi):
        parser.error("--cell-spread needs --interlocking (and no --psi)")
    if args.free_xi and not args.interlocking:
        parser.error("--free-xi needs --interlocking")
    coords = (law + names + (INTERLOCKING if args.interlocking else ()) + (XI if args.free_xi else ())
              + (PSI if args.psi else ())
              + (SPREAD if args.cell_spread else ()) + (KN_EXPONENT if args.fit_kn_exponent else ()))
    if args.fit_kn_exponent and args.law != "linear":
        parser.error("--fit-kn-exponent needs the linear law")
    lo = np.array([BOUNDS[c][0] for c in coords])
    hi = np.array([BOUNDS[c][1] for c in coords])
    evaluations = [0]
    seen = {"deadline": math.inf, "chi_square": math.inf, "x": None, "calls": 0}

    def residuals(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        if time.perf_counter() > seen["deadline"]:
            raise _OutOfTime
        curves = []
        Xs, n_kn = (X[:, :-1], X[:, -1]) if args.fit_kn_exponent else (X, args.kn_exponent)
        for test in tests:
            c, _ = simulate(test, Xs, names, settings, args.plain, args.interlocking, psi=args.psi,
                            spread=args.cell_spread, xi=args.free_xi, kn_exponent=n_kn)
            curves.append({"q": c.q, "p": c.p, "eps_v": c.eps_v})
        evaluations[0] += X.shape[0]
        r = bayes.residuals(tests, curves, NOISE)
        if args.peak_sigma > 0:
            r = np.hstack([r] + [((soft_peak_strain(t.eps1, c["q"]) - soft_peak_strain(t.eps1, t.observed["q"]))
                                  / args.peak_sigma)[:, None] for t, c in zip(tests, curves)])
        r = np.where(np.isfinite(r), r, 1e3)
        chi = np.sum(r ** 2, axis=1)
        seen["calls"] += X.shape[0] == 1
        if chi.min() < seen["chi_square"]:
            seen.update(chi_square=float(chi.min()), x=X[int(np.argmin(chi))].copy())
            print(f"  set {evaluations[0]}: chi-square {chi.min():.4g}", file=sys.stderr, flush=True)
        return r

    start.MAP_MAX_EVALUATIONS = args.max_nfev
    if args.fd_step > 0:
        start.MAP_STEP = args.fd_step
    cell = "plain cell" if args.plain else "critical state (" + ", ".join(names or ("DEFAULTS[3]",)) + " fitted)"
    if args.interlocking:
        cell += " + interlocking friction (m, e_gamma, lambda_c fitted)"
    if args.psi:
        cell += " + map on psi (lambda_psi fitted)"
    if args.free_xi:
        cell += " + xi fitted"
    if args.cell_spread:
        cell += " + cells' friction spread (cell_spread fitted)"
    cell += ", Hertz-Mindlin law" if args.law == "hertz-mindlin" else ""
    cell += f", kn (p0 / p_ref)^{args.kn_exponent:g}" if args.kn_exponent and not args.fit_kn_exponent else ""
    cell += ", kn (p0 / p_ref)^n (n fitted)" if args.fit_kn_exponent else ""
    cell += f", strain at peak fitted (sigma {args.peak_sigma:g})" if args.peak_sigma > 0 else ""
    print(f"split {args.split}, {cell}, kinematics {args.kinematics}; forward: Lebedev {settings.lebedev_order} x "
          f"{settings.n_spins}, increment {settings.increment:g}, iso {settings.iso_increment:g}; nice "
          f"{os.nice(0)}, load {os.getloadavg()[0]:.1f}", flush=True)
    started = time.perf_counter()
    fits = []
    for a0 in (float(v) for v in args.starts.split(",")):
        given = dict(item.split("=") for item in args.start.split(",") if item)
        x0 = np.array([float(given.get(c, args.kn_exponent if c == "kn_exponent" else START[c])) for c in coords])
        if not args.void_ratio:
            x0[3] = a0
        t0 = time.perf_counter()
        if args.max_nfev == 0:  # evaluate the start only
            fits.append({"start_alpha0": a0, "chi_square": float("nan"), "x": x0.tolist(), "nfev": 0, "seconds": 0.0})
            continue
        seen.update(deadline=t0 + args.max_seconds if args.max_seconds > 0 else math.inf, chi_square=math.inf,
                    x=None, calls=0)
        try:
            chi_square, result = start.least_squares_fit(residuals, np.clip(x0, lo, hi), lo, hi)
            x_fit, nfev, stopped, why = result.x, int(result.nfev), False, str(result.message)
        except _OutOfTime:  # --max-seconds: the lowest set run so far
            chi_square, x_fit, nfev, stopped, why = seen["chi_square"], seen["x"], int(seen["calls"]), True, "--max-seconds"
        fits.append({"start_alpha0": a0, "chi_square": chi_square, "x": x_fit.tolist(), "nfev": nfev,
                     "stopped_at_max_seconds": stopped, "termination": why, "fd_step": start.MAP_STEP, "seconds": time.perf_counter() - t0})
        print(f"fit from alpha0 {a0:g}: chi-square {chi_square:.4g} at " + ", ".join(
            f"{c} {v:.4g}" for c, v in zip(coords, x_fit)) + f" ({nfev} iterations, "
            f"{time.perf_counter() - t0:.0f} s" + (", stopped at --max-seconds: lowest set so far" if stopped else
                                                    f"; {why}") + ")", flush=True)
    best = min(fits, key=lambda f: f["chi_square"]) if args.max_nfev else fits[0]
    x = np.array(best["x"])[None, :]
    rows, chi2, curves_out = {}, 0.0, {}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = load(name, args.void_ratio)
        stats: dict = {}
        xs, n_kn = (x[:, :-1], x[:, -1]) if args.fit_kn_exponent else (x, args.kn_exponent)
        c, count = simulate(test, xs, names, settings, args.plain, args.interlocking, stats, args.psi, args.cell_spread,
                            args.free_xi, n_kn)
        if name in fitted:
            chi2 += float(np.sum(bayes.residuals([test], [{"q": c.q, "p": c.p, "eps_v": c.eps_v}], NOISE) ** 2))
        rows[name] = {"role": "predicted" if name == predicted else "fitted", **row(test, c, 0, int(count[0])),
                      "eps1_soft_peak_model": float(soft_peak_strain(test.eps1, c.q[:1])[0]),
                      "eps1_soft_peak_data": float(soft_peak_strain(test.eps1, test.observed["q"])[0])}
        if name in fitted and args.peak_sigma > 0:
            chi2 += ((rows[name]["eps1_soft_peak_model"] - rows[name]["eps1_soft_peak_data"]) / args.peak_sigma) ** 2
        if stats:
            rows[name].update(friction_shear_start=float(stats["friction_shear_start"][0]),
                              friction_end=float(stats["friction_end"][0]), e_c_floored=int(stats["floored"][0]),
                              friction_fallbacks=int(stats["fallbacks"][0]))
        curves_out[name] = {"eps1": test.eps1.tolist(), "q": c.q[0].tolist(), "eps_v": c.eps_v[0].tolist(),
                            "q_data": test.observed["q"].tolist(), "eps_v_data": test.observed["eps_v"].tolist()}
    seconds = time.perf_counter() - started
    optimum = {c: float(v) for c, v in zip(coords, x[0])}
    print(f"optimum: " + ", ".join(f"{c} {v:.4g}" for c, v in optimum.items())
          + f"; chi-square fitted {chi2:.4g}; {evaluations[0]} sets, {seconds:.0f} s, load {os.getloadavg()[0]:.1f}")
    print_prediction_table(rows, fallbacks=True)
    print("smoothed strain at peak (soft_peak_strain) model / data [%]: " + ", ".join(
        f"{k} {100 * v['eps1_soft_peak_model']:.2f} / {100 * v['eps1_soft_peak_data']:.2f}" for k, v in rows.items()))
    if args.interlocking:
        print("interlocking friction [deg] at the start of shear -> at the end (increments with e_c clipped, with "
              "the friction back at phi_mu): " + ", ".join(
                  f"{k} {v['friction_shear_start']:.2f} -> {v['friction_end']:.2f} ({v['e_c_floored']}, "
                  f"{v['friction_fallbacks']})" for k, v in rows.items()))
    print("renewals per point: " + ", ".join(f"{k} {v['renewals']}" for k, v in rows.items())
          + "; d eps_v / d eps1 over the last five points: "
          + ", ".join(f"{k} {v['dilatancy_end']:+.2f}" for k, v in rows.items()))
    out = {"split": args.split, "cell": cell, "start": args.start, "void_ratio": args.void_ratio, "kinematics": args.kinematics, "rule_params": list(names),
           "interlocking": {"xi": "fitted" if args.free_xi else Interlocking().xi, "p_ref": Interlocking().p_ref}
           if args.interlocking else None,
           "rule_defaults": {k: v for k, v in RULE.__dict__.items() if isinstance(v, (int, float, str))},
           "settings": {"lebedev_order": settings.lebedev_order, "n_spins": settings.n_spins,
                        "increment": settings.increment, "iso_increment": settings.iso_increment,
                        "stress_rtol": settings.stress_rtol}, "noise": NOISE,
           "law": args.law, "kn_exponent": args.kn_exponent, "peak_sigma": args.peak_sigma, "optimum": optimum, "chi_square_fitted": chi2, "fits": fits, "tests": rows, "curves": curves_out,
           "evaluations": evaluations[0], "seconds": seconds, "load_average_at_end": list(os.getloadavg())}
    stem = f"real_sand_critical_state_{args.split.replace('+', '_')}" + (f"_{args.tag}" if args.tag else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(out, indent=1))
    figure(out, RESULTS / f"{stem}.png")
    return 0


def figure(out: dict, path: Path) -> None:
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (ax_q, ax_v) = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, (name, c) in enumerate(out["curves"].items()):
        colour = f"C{k}"
        role = out["tests"][name]["role"]
        e = 100 * np.asarray(c["eps1"])
        label = f"{name.split('_')[1].replace('kpa.csv', ' kPa')} ({role})"
        style = "--" if role == "predicted" else "-"
        ax_q.plot(e, np.asarray(c["q_data"]) / 1e3, ".", color=colour, ms=3)
        ax_q.plot(e, np.asarray(c["q"]) / 1e3, style, color=colour, label=label)
        ax_v.plot(e, 100 * np.asarray(c["eps_v_data"]), ".", color=colour, ms=3)
        ax_v.plot(e, 100 * np.asarray(c["eps_v"]), style, color=colour)
    ax_q.set(xlabel="eps1 [%]", ylabel="q [kPa]")
    ax_v.set(xlabel="eps1 [%]", ylabel="eps_v [%] (contraction > 0)")
    ax_q.legend(fontsize=8)
    fig.suptitle(f"Dobrany sand, split {out['split']}: {out['cell']}, kinematics {out['kinematics']} "
                 "(dots: data; lines: model)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
