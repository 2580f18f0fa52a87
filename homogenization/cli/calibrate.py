"""hmodel calibrate --data a.csv [--data b.csv] --backend analytical --params phi_g,kn,kt_over_kn,alpha0 [--prior FILE] --out DIR

(also ``python -m homogenization.calibrate``.) Bayesian calibration of the H-model's
micro-parameters on measured biaxial (2D) or triaxial (3D) curves (format:
``homogenization.calibration.data``; worked example: docs/calibration.md). Every --data test is
fitted jointly; the parameters not in --params keep the values of --phi, --kn, --kt and --alpha0.
--law hertz-mindlin (triaxial data) calibrates phi_g, shear_modulus, poisson and alpha0 instead
(default prior PRIOR_BOUNDS_HERTZ_3D; posterior.json then holds ``contact_law``). alpha0_spread
(triaxial data, analytical backend, --confirm none) adds a uniform distribution of opening
angles of that half-width [deg] about alpha0 (``homogenization.material.opening_spread``).
--critical-state runs the cells' renewal rule (``homogenization.material.critical_state``, its
defaults for the data's dimension) in the forward model; its alpha_c [deg] and renewal_rate [-] may
then be calibrated; posterior.json holds the rule at the posterior mean (``critical_state``), which
``hmodel triaxial --posterior`` and ``hmodel biaxial --posterior`` run. --interlocking (triaxial data,
analytical backend, --confirm none) adds the interlocking friction (``homogenization.calibration.interlocking``):
its interlocking_m, e_gamma, lambda_c, xi_c, cell_spread, mobilisation_strain, mobilisation_start,
mobilisation_exponent and mobilisation_void_slope (the friction's hyperbolic mobilisation with the point's
distortion, over a strain growing with the pressure and the test's void ratio), relax_strain, relax_exponent and
relax_void_slope (the void ratio it reads lagging over a distortion growing with the pressure and the test's void
ratio), softening_strain (that lag from the point's densest state on instead) and map_state_weight (each test's cell
built at the map's alpha0 of e0 + w lambda_c ((p0 / 101.325 kPa)^xi_c - 1) instead of e0's; data with void ratios) and
stiffness_void_slope (each test's kn times exp(-s_k (e0 - 0.55)); linear law) may then be calibrated, the others
fixed by --interlocking-values; posterior.json holds it at the posterior mean (``interlocking``), which ``hmodel
triaxial --posterior`` runs. --kn-exponent N runs each triaxial test at kn (p0 / 101.325 kPa)^N; --params kn_exponent
calibrates N instead. --start-point starts the map fit at given values instead of prior draws.

The posterior is sampled with emcee's ensemble (--moves: its stretch move or differential evolution), every
step running the forward model of all walkers as one batch of cells. --start map (default) first finds the posterior's
main mode by a seeded multi-start least-squares fit and starts the walkers around it
(``homogenization.calibration.start``); --start prior starts them at the best prior draws. At
the end the DEM runs once at the posterior mean (--confirm dem) and its misfit is reported.

DIR receives: chain.h5 (emcee's backend: the whole chain, resumable), posterior.h5 (retained
samples in CLI units, log posterior), posterior.json (mean, median, ci95 per parameter in the
CLI flags' units), corner.png, fits.png, run.json (identifiability, correlations, diagnostics,
provenance). The same settings resume the chain up to --steps (fewer steps than it holds are refused); other
settings need --overwrite, which restarts it.

Bad input (missing or malformed file, unknown parameter or one the backend cannot vary, a
folder holding other files or being written by another calibration, an unwritable --out) is one
line on stderr and exit code 2, before any run. Ctrl-C or ``kill`` is one line and exit code
130; chain.h5 keeps every finished step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from homogenization.ann import RANGE_MODELS
from homogenization.backends import BACKENDS
from homogenization.calibration import bayes
from homogenization.calibration.data import Measurement, read_test
from homogenization.calibration.forward import (DENSITY, INTERLOCKING, KN_EXPONENT, LAW_PARAMETERS, MAP_STATE,
                                                PARAMETERS, RULE, SPREAD, STIFFNESS, ForwardSettings, calibratable,
                                                check_density, density_alpha0, settings_record, with_density)
from homogenization.calibration.interlocking import Interlocking
from homogenization.material.density import DEFAULT_E_MAX, DEFAULT_E_MIN
from homogenization.material import opening_spread
from homogenization.calibration.start import START_METHODS, refit_start
from homogenization.cli.options import (
    add_critical_state_argument,
    add_orientations_argument,
    add_spatial_rule_arguments,
    add_threads_argument,
    add_uncertified_argument,
    command_parser,
    critical_state_rule,
    refuse_uncertified_file,
)
from warp_hcell.core.cli import (
    UserError,
    add_contact_law_arguments,
    alpha0_deg,
    contact_law_from_args,
    finite_float,
    fraction,
    non_negative_float,
    positive_float,
    positive_int,
    progress_bar,
    say,
    set_verbosity,
)
from warp_hcell.core.dimension import dimension
from warp_hcell.core.files import check_output_path, output_lock, temporary_of
from warp_hcell.core.provenance import file_sha256
from warp_hcell.core.parameters import ContactLaw, HertzMindlinLaw

RESOLUTION_MODES = ("correct", "check", "off")
"""--resolution choices (``homogenization.calibration.resolution``)."""
CHAIN_FILE = "chain.h5"
OUTPUT_FILES = (CHAIN_FILE, "posterior.h5", "posterior.json", "corner.png", "fits.png", "run.json")
"""Everything this command writes into DIR."""
FORWARD = ForwardSettings(n_orientations=36, increment=1e-3, iso_increment=1e-3, stress_rtol=1e-5)
"""Defaults of the forward model: coarse, its bias measured against the fine setting (docs/calibration.md)."""


def parameter_list(text: str) -> tuple[str, ...]:
    """argparse type: comma list of ``PARAMETERS`` (duplicates dropped, order kept)."""
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise argparse.ArgumentTypeError(f"give at least one of {','.join(PARAMETERS)}")
    for name in names:
        if name not in PARAMETERS:
            raise argparse.ArgumentTypeError(f"unknown parameter {name!r}; choose from {','.join(PARAMETERS)}")
    return names


def prior_text(bounds: dict[str, tuple[float, float, bool]]) -> str:
    """Help text of default prior bounds: "phi_g [10, 45], kn [5e+07, 5e+09] log, ..."."""
    return ", ".join(f"{k} [{lo:g}, {hi:g}]{' log' if lg else ''}" for k, (lo, hi, lg) in bounds.items())


def build_parser() -> argparse.ArgumentParser:
    """Parser of the calibrate command."""
    parser = command_parser("homogenization.calibrate",
                            "Bayesian calibration of the H-model's micro-parameters on measured biaxial or triaxial curves.")
    parser.add_argument("--data", type=Path, action="append", required=True,
                        help="measured curve (CSV: '# test = undrained|drained|triaxial_undrained|triaxial_drained', "
                             "'# p0 = ...', header eps1 and any of q, p, eps_v); repeat for a joint fit")
    parser.add_argument("--backend", choices=tuple(BACKENDS), default="analytical", help="forward model")
    parser.add_argument("--params", type=parameter_list, required=True,
                        help="parameters to calibrate, comma list of those of the contact law: "
                             + "; ".join(f"{law}: {','.join(calibratable(law))}" for law in LAW_PARAMETERS)
                             + f" ({SPREAD}: triaxial data, analytical backend)")
    parser.add_argument("--prior", type=Path, default=None,
                        help="JSON prior: parameter -> [low, high] or {low, high, log} (default bounds, biaxial data: "
                             + prior_text(bayes.DEFAULT_BOUNDS[2]) + "; with triaxial data: "
                             + prior_text(bayes.DEFAULT_BOUNDS[3]) + "; with --law hertz-mindlin: "
                             + prior_text(bayes.HERTZ_BOUNDS) + f"; {SPREAD} [{bayes.SPREAD_PRIOR[0]:g}, "
                             f"{bayes.SPREAD_PRIOR[1]:g}], cut by alpha0 - {SPREAD} >= 45)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (resumed if it holds this calibration)")
    parser.add_argument("--alpha0", type=alpha0_deg, default=FORWARD.fixed["alpha0"],
                        help="alpha0 [deg] where not calibrated")
    parser.add_argument("--alpha0-spread", type=float, default=0.0,
                        help="half-width [deg] of each point's uniform distribution of opening angles about alpha0 "
                             f"({opening_spread.N_NODES} families of cells; triaxial data; with --critical-state each "
                             "family renews on its own void ratio) where not calibrated; 0: one opening angle")
    parser.add_argument("--e-min", type=float, default=DEFAULT_E_MIN,
                        help="void ratio of the densest cell [-] where not calibrated (data files with '# void_ratio = E')")
    parser.add_argument("--e-max", type=float, default=DEFAULT_E_MAX,
                        help="void ratio of the loosest cell [-] where not calibrated (data files with '# void_ratio = E')")
    add_critical_state_argument(parser)
    add_contact_law_arguments(parser)
    sampler = parser.add_argument_group("sampler")
    sampler.add_argument("--walkers", type=positive_int, default=32, help="ensemble size (>= 2 x number of parameters)")
    sampler.add_argument("--steps", type=positive_int, default=600, help="ensemble steps in total (resume extends)")
    sampler.add_argument("--moves", choices=tuple(bayes.MOVES), default="stretch",
                         help="the ensemble's moves: stretch (default, emcee's) = a walker moves along the line "
                              "through another; de = differential evolution, a walker moves along the difference "
                              "of two others (80 %%) or by a snooker update (20 %%). Pick de where stretch's "
                              "autocorrelation time is long on a smooth posterior (2.7x shorter on a 2-parameter "
                              "known truth); on the rough 14-parameter Dobrany fit both were the same "
                              "(docs/studies/calibration_sampler_moves.md)")
    sampler.add_argument("--burn", type=fraction, default=0.5, help="fraction of the steps discarded as burn-in")
    sampler.add_argument("--start", choices=tuple(START_METHODS), default="map",
                         help="where the walkers start: map = a ball around the best of a seeded multi-start "
                              "least-squares fit (default: no walker starts in a secondary mode), prior = the best "
                              "of 8 x --walkers prior draws")
    sampler.add_argument("--start-point", type=start_point_values, default=None, metavar="NAME=VALUE,...",
                         help="--start map: one least-squares fit from these values (CLI units) of every calibrated "
                              "parameter instead of the fits from prior draws (e.g. a previous optimum)")
    sampler.add_argument("--start-scales", type=start_scales, default=None, metavar="NAME=F1,F2,...",
                         help="with --start-point: one least-squares fit from the point with NAME times each factor "
                              "F (the others as given), the lowest chi-square kept (every fit recorded in run.json); "
                              "for a rough objective whose fits stop near their start (e.g. kn=0.6,0.7,0.8,0.9,1)")
    sampler.add_argument("--noise", type=positive_float, default=0.02,
                         help="measurement error sd as a fraction of each channel's largest abs value")
    sampler.add_argument("--model-error", type=non_negative_float, default=0.0, metavar="FRACTION",
                         help="model error sd as a fraction of each channel's largest abs value, added in quadrature "
                              "to --noise (the likelihood's sigma); the run suggests a value where the fit misses the "
                              "data far above their noise (default 0)")
    forward = parser.add_argument_group("forward model")
    add_orientations_argument(forward, FORWARD.n_orientations, "cell orientations")
    add_spatial_rule_arguments(forward, FORWARD.lebedev_order, FORWARD.n_spins, " (triaxial data)")
    forward.add_argument("--staggered-spins", action="store_true",
                         help="triaxial data: stagger the spins from axis to axis (default aligned: the rule's cube "
                              "symmetry kept)")
    forward.add_argument("--increment", type=positive_float, default=FORWARD.increment, help="shear strain increment [-]")
    forward.add_argument("--iso-increment", type=positive_float, default=FORWARD.iso_increment,
                         help="isotropic strain increment per component [-]")
    forward.add_argument("--stress-rtol", type=positive_float, default=FORWARD.stress_rtol,
                         help="relative tolerance of p = p0 and drained sigma22 = p0 [-]")
    forward.add_argument("--kn-exponent", type=kn_exponent, default=0.0, metavar="N",
                         help="linear law, triaxial data: each test runs kn (p0 / 101.325 kPa)^N, a contact stiffness "
                              "growing with its confining pressure (kn and its prior: the value at 101.325 kPa; N in "
                              "[0, 1], 0.5 as a sand's small-strain stiffness; default 0: one kn for every test; or "
                              "calibrate N: --params kn_exponent, default prior [0, 1])")
    forward.add_argument("--interlocking", action="store_true",
                         help="triaxial data, analytical backend, --confirm none: each point's contact friction "
                              "tan phi = (e_c(p) / e)^m tan phi_g, e its void ratio, e_c(p) = e_gamma - lambda_c "
                              "(p / 101.325 kPa)^xi_c (Chang & Hicher 2005), its cells spread by +-cell_spread about "
                              "it, mobilised over a strain mobilisation_strain (p / 101.325 kPa)^mobilisation_exponent "
                              "exp(mobilisation_void_slope (e0 - 0.55)) (default exponent 2/3) from "
                              "mobilisation_start of it (default 0: at once), e lagging over a distortion "
                              "relax_strain (p / 101.325 kPa)^relax_exponent exp(relax_void_slope (e0 - 0.55)), e0 "
                              "the test's void ratio (default 0: no lag; softening_strain "
                              "instead: lagging from the densest state on), each test's cell at the void-ratio map's "
                              "alpha0 of e0 + map_state_weight lambda_c ((p0 / 101.325 kPa)^xi_c - 1) (default 0: of "
                              "e0), kn times exp(-stiffness_void_slope (e0 - 0.55)) (default 0: kn); calibrate "
                              "interlocking_m, e_gamma, lambda_c, xi_c, cell_spread, mobilisation_strain, "
                              "mobilisation_start, relax_strain, relax_exponent, softening_strain, relax_void_slope, "
                              "mobilisation_exponent, mobilisation_void_slope, map_state_weight, "
                              "stiffness_void_slope through --params "
                              "(docs/calibration.md)")
    forward.add_argument("--interlocking-values", type=interlocking_values, default=None, metavar="NAME=VALUE,...",
                         help="with --interlocking: values of its parameters not calibrated (default "
                              + ",".join(f"{n}={getattr(Interlocking(), f):g}" for n, f in INTERLOCKING.items())
                              + ")")
    forward.add_argument("--resolution", choices=RESOLUTION_MODES, default="correct",
                         help="check the forward model's discretisation error against the noise at the start "
                              "point and at the optimum: correct (default) = where it is not well below the noise, "
                              "refine a copy at that point until it is and add the difference to every curve; "
                              "check = refuse (exit 2) naming the --increment and --orientations it needs; off = "
                              "no check")
    add_threads_argument(forward, "CPU threads of the DEM (dem, --confirm)")
    forward.add_argument("--workers", type=positive_int, default=1,
                         help="processes that share each forward run's parameter sets, or its tests where there are "
                              "fewer sets (analytical backend): the same curves as one process; 1.4-1.6x faster with 2 "
                              "on 2 free cores (docs/calibration.md)")
    parser.add_argument("--confirm", choices=("dem", "none"), default="dem",
                        help="run the DEM once at the posterior mean and report its misfit")
    parser.add_argument("--confirm-orientations", type=positive_int, default=36, help="orientations of the DEM check")
    add_uncertified_argument(parser)
    return parser


def read_tests(paths: Sequence[Path]) -> list[Measurement]:
    """Every data file, parsed before any run; UserError (one line) on the first bad one."""
    tests = []
    for path in paths:
        try:
            tests.append(read_test(path))
        except ValueError as exc:
            raise UserError(str(exc)) from None
    names = [t.name for t in tests]
    if len(set(names)) != len(names):
        raise UserError(f"two --data files share the name {next(n for n in names if names.count(n) > 1)!r}")
    return tests


def check_out(out: Path, overwrite: bool) -> None:
    """UserError (one line) unless ``out`` is a folder that can be created or written and that holds
    only this command's files (and temporaries of its atomic writes)."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder")
    check_output_path(out, overwrite=True)  # its nearest existing parent is a writable folder
    if not out.exists():
        return
    foreign = sorted(p.name for p in out.iterdir() if p.name not in OUTPUT_FILES and temporary_of(p) is None)
    if foreign:
        raise UserError(f"{out} holds files that this command did not write ({', '.join(foreign[:3])}); "
                        f"choose another --out")


def configuration(args: argparse.Namespace, tests: Sequence[Measurement], prior: bayes.Prior,
                  settings: ForwardSettings) -> dict[str, Any]:
    """What defines the chain: a resumed run must match it."""
    return {
        "data": {t.name: file_sha256(t.path) for t in tests},
        "params": list(prior.names),
        "prior": prior.to_dict(),
        "noise": args.noise,
        "walkers": args.walkers,
        "seed": args.seed,
        "start": args.start,
        "forward": forward_config(settings),
        # new keys only where not default, so that the chains of earlier runs still resume
        **({"model_error": args.model_error} if args.model_error else {}),
        **({"resolution": args.resolution} if args.resolution != "correct" else {}),
        **({"start_point": dict(args.start_point)} if args.start_point is not None else {}),
        **({"start_scales": {args.start_scales[0]: list(args.start_scales[1])}} if args.start_scales else {}),
        **({"moves": args.moves} if args.moves != "stretch" else {}),
    }


def forward_config(settings: ForwardSettings) -> dict[str, Any]:
    """The forward model's settings as run.json and chain.h5 store them; the linear law, the default,
    is not named (as ``ContactLaw.to_dict``), so that a linear chain's settings read the same as ever."""
    config = {**settings_record(settings), "backend_options": {}}
    if settings.law == ForwardSettings.law:
        del config["law"]
    return config


def forward_settings(args: argparse.Namespace, dim: int = 2) -> ForwardSettings:
    """The forward model of the flags; ``dim``: the data's dimension (the critical-state rule's ``DEFAULTS[dim]``)."""
    law = contact_law_from_args(args)
    if law.name == HertzMindlinLaw.name:
        fixed = {"phi_g": law.phi_g_deg, "shear_modulus": law.shear_modulus, "poisson": law.poisson,
                 "alpha0": args.alpha0}
    else:
        fixed = {"phi_g": law.phi_g_deg, "kn": law.kn, "kt_over_kn": law.kt_over_kn, "alpha0": args.alpha0}
    if args.alpha0_spread != 0.0:
        fixed[SPREAD] = args.alpha0_spread
    options: dict[str, Any] = {}
    if args.backend in ("dem", "ann"):
        options["device"] = args.device
    if args.threads is not None and args.backend in ("dem", "ann"):
        options["threads"] = args.threads
    return ForwardSettings(law=law.name, backend=args.backend, n_orientations=args.orientations,
                           lebedev_order=args.order, n_spins=args.spins, staggered_spins=args.staggered_spins,
                           increment=args.increment,
                           iso_increment=args.iso_increment, radius=args.radius, stress_rtol=args.stress_rtol,
                           fixed=fixed, backend_options=options,
                           critical_state=critical_state_rule(dim, args.renewal_phases) if args.critical_state else None,
                           kn_exponent=args.kn_exponent,
                           interlocking=interlocking_settings(args) if args.interlocking else None)


def check_args(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    law_parameters = calibratable(args.law)
    wrong = [name for name in args.params if name not in law_parameters]
    if wrong:
        raise UserError(f"--params {wrong[0]} is not a parameter of the {args.law} contact law (--law {args.law}: "
                        f"{','.join(law_parameters)})")
    if args.law == HertzMindlinLaw.name:
        flat = [t.name for t in tests if t.dim != 3]
        if flat:
            raise UserError(f"--law {args.law} is defined for spheres: --data {flat[0]} is biaxial (2D); give "
                            f"triaxial data")
        if args.backend == "ann":
            raise UserError("--backend ann is trained on the linear contact law: --law hertz-mindlin needs "
                            "--backend analytical or dem")
    check_spread(args, tests)
    check_fixed_alpha0(args, tests)
    check_critical_state(args, tests)
    check_kn_exponent(args, tests)
    check_interlocking(args, tests)
    if args.start_point is not None:
        missing = [n for n in args.params if n not in args.start_point]
        extra = [n for n in args.start_point if n not in args.params]
        if args.start != "map" or missing or extra:
            raise UserError(f"--start-point gives the --start map fit a value of every calibrated parameter and no "
                            f"other ({'--start ' + args.start if args.start != 'map' else 'missing ' + ','.join(missing) if missing else 'not calibrated: ' + ','.join(extra)})")
    if args.start_scales is not None:
        name, factors = args.start_scales
        if args.start_point is None or name not in args.params:
            raise UserError(f"--start-scales {name}=...: scales a calibrated parameter of --start-point "
                            f"({'no --start-point' if args.start_point is None else name + ' is not in --params'})")
    if args.backend == "ann" and set(args.params) - {"alpha0"}:
        raise UserError("--backend ann is trained on one contact law: it can calibrate alpha0 only; use analytical")
    if args.backend == "ann" and not all(RANGE_MODELS[t.dim] for t in tests):
        raise UserError("--backend ann has no 3D model of a range of opening angles (the shipped one is trained at "
                        "alpha0 = 55 deg only): triaxial data need --backend analytical or dem")
    if args.backend == "ann":
        refuse_uncertified_file(None, args)
    if args.workers > 1 and args.backend != "analytical":
        raise UserError(f"--workers {args.workers} shares the analytical backend's forward runs; --backend "
                        f"{args.backend} takes --threads")
    if args.walkers < 2 * len(args.params):
        raise UserError(f"--walkers {args.walkers} must be >= 2 x the {len(args.params)} parameters")
    if args.increment > min(float(t.eps1.max()) for t in tests):
        raise UserError(f"--increment {args.increment:g} is larger than the strain range of a data file")
    if args.iso_increment >= 0.1:
        raise UserError(f"--iso-increment {args.iso_increment:g} must be < 0.1")


def check_fixed_alpha0(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    """UserError (one line) for a fixed --alpha0 below the ten-sphere cell's least opening with a triaxial test that
    runs at it (one without its void ratio, which would run at the void-ratio map's alpha0)."""
    floor = {t.name: dimension(t.dim).min_opening_deg or 0.0 for t in tests if t.void_ratio is None}
    below = [name for name, least in floor.items() if args.alpha0 < least]
    if "alpha0" not in args.params and below:
        raise UserError(f"--alpha0 {args.alpha0:g}: triaxial data ({below[0]}) need alpha0 >= {floor[below[0]]:g} deg "
                        f"(below, the ten-sphere cell's two planes overlap)")


def check_critical_state(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    """UserError (one line) for the rule's parameters (``RULE``) calibrated without --critical-state, or
    --critical-state with data of both dimensions."""
    rule = [name for name in args.params if name in RULE]
    if rule and not args.critical_state:
        raise UserError(f"--params {rule[0]} is a parameter of the critical-state rule; add --critical-state")
    if not args.critical_state:
        if args.renewal_phases is not None:
            raise UserError("--renewal-phases needs --critical-state (the rule whose renewals it groups)")
        return
    if len({t.dim for t in tests}) > 1:
        raise UserError("--critical-state: the rule's defaults differ between biaxial and triaxial cells; give data "
                        "of one dimension")


def check_kn_exponent(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    """UserError (one line) for --kn-exponent or a calibrated kn_exponent where it has no meaning: a law other than
    the linear one, biaxial data (their p0 is a force per length) or --backend ann (trained at one kn); or both."""
    if KN_EXPONENT in args.params:
        flat = [t.name for t in tests if t.dim != 3]
        if args.kn_exponent != 0.0:
            raise UserError(f"--kn-exponent {args.kn_exponent:g} with --params {KN_EXPONENT}: the exponent is "
                            f"calibrated; drop --kn-exponent")
        if flat:
            raise UserError(f"--params {KN_EXPONENT} needs triaxial data (a confining pressure in Pa): --data "
                            f"{flat[0]} is biaxial")
        if args.backend == "ann":
            raise UserError(f"--params {KN_EXPONENT} with --backend ann: the ANN is trained at one kn; use analytical "
                            f"or dem")
        return
    if args.kn_exponent == 0.0:
        return
    if args.law != ForwardSettings.law:
        raise UserError(f"--kn-exponent scales the linear law's kn; --law {args.law} has its own pressure dependence")
    flat = [t.name for t in tests if t.dim != 3]
    if flat:
        raise UserError(f"--kn-exponent needs triaxial data (a confining pressure in Pa): --data {flat[0]} is biaxial")
    if args.backend == "ann":
        raise UserError("--kn-exponent with --backend ann: the ANN is trained at one kn; use analytical or dem")


def name_values(text: str, names: Sequence[str], flag: str) -> dict[str, float]:
    """argparse helper: "a=1,b=2" -> {"a": 1.0, "b": 2.0}, every name one of ``names``."""
    out: dict[str, float] = {}
    for item in (i.strip() for i in text.split(",") if i.strip()):
        name, sep, value = item.partition("=")
        if not sep or name.strip() not in names:
            raise argparse.ArgumentTypeError(f"{item!r} is not NAME=VALUE with NAME one of {','.join(names)}")
        out[name.strip()] = finite_float(value)
    if not out:
        raise argparse.ArgumentTypeError(f"give NAME=VALUE,... ({flag})")
    return out


def interlocking_values(text: str) -> dict[str, float]:
    """argparse type of --interlocking-values: NAME=VALUE,... of ``INTERLOCKING``'s names, floats."""
    return name_values(text, tuple(INTERLOCKING), "--interlocking-values")


def start_point_values(text: str) -> dict[str, float]:
    """argparse type of --start-point: NAME=VALUE,... of ``PARAMETERS``, floats (CLI units)."""
    return name_values(text, PARAMETERS, "--start-point")


def check_start_scales(args: argparse.Namespace, prior: bayes.Prior) -> None:
    """UserError (one line) where a --start-point value, or a --start-scales factor of it, lies outside the prior
    (the fit would start clipped to its bound)."""
    for name, value in (args.start_point or {}).items():
        k = prior.names.index(name)
        if not prior.low[k] <= value <= prior.high[k]:
            raise UserError(f"--start-point {name}={value:g} is outside the prior [{prior.low[k]:g}, {prior.high[k]:g}]")
    if args.start_scales is None:
        return
    name, factors = args.start_scales
    k = prior.names.index(name)
    for factor in factors:
        value = args.start_point[name] * factor
        if not prior.low[k] <= value <= prior.high[k]:
            raise UserError(f"--start-scales {name}={factor:g}: the start {name} = {value:g} is outside the prior "
                            f"[{prior.low[k]:g}, {prior.high[k]:g}]")


def start_scales(text: str) -> tuple[str, tuple[float, ...]]:
    """argparse type of --start-scales: "NAME=F1,F2,..." -> (NAME, (F1, F2, ...)), NAME one of ``PARAMETERS``, each
    factor finite and > 0."""
    name, sep, rest = text.partition("=")
    factors = tuple(finite_float(f) for f in rest.split(",") if f.strip()) if sep else ()
    if name.strip() not in PARAMETERS or not factors or min(factors) <= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=F1,F2,... with NAME one of {','.join(PARAMETERS)} "
                                         f"and factors > 0")
    return name.strip(), factors


def interlocking_settings(args: argparse.Namespace) -> Interlocking:
    """The ``Interlocking`` of --interlocking-values (its defaults elsewhere)."""
    return replace(Interlocking(), **{INTERLOCKING[n]: v for n, v in (args.interlocking_values or {}).items()})


def check_interlocking(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    """UserError (one line) for the interlocking friction's parameters or --interlocking-values without
    --interlocking, or --interlocking with biaxial data (its p_ref is a pressure), a backend other than the
    analytical one, --confirm dem (the DEM's contacts keep phi_g), both lags calibrated, a value
    out of range, relax_void_slope, mobilisation_void_slope or map_state_weight calibrated or nonzero with a --data
    file that gives no void ratio, mobilisation_exponent or mobilisation_void_slope calibrated or not at its default
    without mobilisation_strain calibrated or nonzero, map_state_weight calibrated or nonzero on a flat line
    (lambda_c 0, not calibrated), or stiffness_void_slope nonzero with a law other than the linear one."""
    own = [name for name in args.params if name in INTERLOCKING]
    if not args.interlocking:
        if MAP_STATE in own:
            raise UserError(f"--params {MAP_STATE} moves the map along the interlocking's critical-state line "
                            f"(lambda_c, xi_c); add --interlocking")
        if own or args.interlocking_values is not None:
            raise UserError(f"{'--params ' + own[0] if own else '--interlocking-values'}: the interlocking friction's; "
                            f"add --interlocking")
        return
    flat = [t.name for t in tests if t.dim != 3]
    if flat:
        raise UserError(f"--interlocking needs triaxial data (a pressure in Pa): --data {flat[0]} is biaxial")
    if args.backend != "analytical" or args.confirm == "dem":
        what = f"--backend {args.backend}" if args.backend != "analytical" else "--confirm dem"
        raise UserError(f"--interlocking: {what} runs the DEM, whose contacts keep phi_g; use --backend analytical "
                        f"--confirm none")
    if "relax_strain" in args.params and "softening_strain" in args.params:
        raise UserError("--params relax_strain,softening_strain: one lag at a time (calibrate one of them)")
    settings = interlocking_settings(args)
    try:
        settings.check()
    except ValueError as exc:
        raise UserError(f"--interlocking-values: {exc}") from None
    unknown = [t.name for t in tests if t.void_ratio is None]
    for name, what in (("relax_void_slope", "the lag"), ("mobilisation_void_slope", "the mobilisation strain")):
        if unknown and (name in args.params or getattr(settings, name) != 0.0):
            raise UserError(f"{name} scales {what} by the test's void ratio: --data {unknown[0]} gives none "
                            f"('# void_ratio = E' in its header)")
    state_map = MAP_STATE in args.params or settings.map_state_weight != 0.0
    if unknown and state_map:
        raise UserError(f"{MAP_STATE} shifts the void ratio that the map reads: --data {unknown[0]} gives none "
                        f"('# void_ratio = E' in its header)")
    if state_map and "lambda_c" not in args.params and settings.lambda_c == 0.0:
        raise UserError(f"{MAP_STATE} moves the map along the critical-state line, flat at lambda_c = 0: calibrate "
                        f"lambda_c or give it (--interlocking-values lambda_c=L, L > 0)")
    if args.law != ContactLaw.name and settings.stiffness_void_slope != 0.0:  # --params: refused by the law's list
        raise UserError(f"{STIFFNESS} scales the linear law's kn: --law {args.law} has none")
    default = Interlocking()
    idle = [n for n in ("mobilisation_exponent", "mobilisation_void_slope")
            if n in args.params or getattr(settings, n) != getattr(default, n)]
    if idle and "mobilisation_strain" not in args.params and settings.mobilisation_strain == 0.0:
        raise UserError(f"{idle[0]} shapes the mobilisation strain: calibrate mobilisation_strain or give it "
                        f"(--interlocking-values mobilisation_strain=A, A > 0)")


def check_interlocking_prior(prior: bayes.Prior, settings: ForwardSettings) -> None:
    """UserError (one line) where the prior of an interlocking parameter reaches outside ``Interlocking.check``."""
    if settings.interlocking is None:
        return
    for name, low, high in zip(prior.names, prior.low, prior.high):
        if name in INTERLOCKING:
            for value in (low, high):
                try:
                    replace(settings.interlocking, **{INTERLOCKING[name]: float(value)}).check()
                except ValueError as exc:
                    raise UserError(f"the prior of {name} reaches {value:g}: {exc}") from None


def kn_exponent(text: str) -> float:
    """argparse type: a float in [0, 1]."""
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be in [0, 1]")
    return value


def check_rule_prior(prior: bayes.Prior, settings: ForwardSettings) -> None:
    """UserError (one line) where the prior of a rule parameter reaches outside what the rule allows
    (``CriticalState.check``: alpha_c within the fresh angles' clip, renewal_rate > 0 and <= rate_max)."""
    if settings.critical_state is None:
        return
    for name, low, high in zip(prior.names, prior.low, prior.high):
        if name in RULE:
            for value in (low, high):
                try:
                    replace(settings.critical_state, **{RULE[name]: float(value)}).check()
                except ValueError as exc:
                    raise UserError(f"the prior of {name} reaches {value:g}: {exc}") from None


def likelihood_noise(args: argparse.Namespace) -> float:
    """The likelihood's sigma as a fraction of each channel's scale: --noise and --model-error in quadrature."""
    return float(np.hypot(args.noise, args.model_error))


def check_spread(args: argparse.Namespace, tests: Sequence[Measurement]) -> None:
    """UserError (one line) for alpha0_spread (calibrated or --alpha0-spread) where the forward model cannot
    run it: biaxial data, a backend other than the analytical one, --confirm dem (the DEM takes one opening
    angle per model), or a fixed spread below 0 or, where a test runs at the fixed --alpha0 (one without its void
    ratio), past alpha0 - 45 deg (``check_spread_at_void_ratios`` judges the others; a calibrated alpha0 the
    prior's cut)."""
    if SPREAD not in args.params and args.alpha0_spread == 0.0:
        return
    if any(t.dim != 3 for t in tests):
        raise UserError(f"{SPREAD}: a spread of opening angles is a parameter of the ten-sphere cell; give triaxial "
                        f"data only")
    if args.backend != "analytical" or args.confirm == "dem":
        what = f"--backend {args.backend}" if args.backend != "analytical" else "--confirm dem"
        raise UserError(f"{SPREAD}: {what} runs one opening angle per model; a spread runs on the analytical backend "
                        f"only (add --confirm none)")
    if SPREAD not in args.params:
        at_fixed_alpha0 = "alpha0" not in args.params and any(t.void_ratio is None for t in tests)
        try:  # an alpha0 of +inf: the sign of the spread alone
            opening_spread.check(args.alpha0 if at_fixed_alpha0 else np.inf, args.alpha0_spread)
        except ValueError as exc:
            raise UserError(f"--alpha0-spread: {exc}") from None


def check_spread_at_void_ratios(args: argparse.Namespace, tests: Sequence[Measurement],
                                settings: ForwardSettings) -> None:
    """UserError (one line) for a fixed --alpha0-spread that a test's void ratio rules out: the test runs at the
    void-ratio map's alpha0 (e_min, e_max and the state map fixed), and that alpha0 minus the spread is below
    45 deg. Where the map is calibrated each set is judged on its own (NaN curves, counted as a failed set)."""
    if SPREAD in args.params or args.alpha0_spread == 0.0:
        return
    if any(name in args.params for name in (*DENSITY, MAP_STATE, "lambda_c", "xi_c")):
        return
    for test in tests:
        alpha0 = density_alpha0(test, {}, settings)
        if alpha0 is None or not np.isfinite(alpha0).all():
            continue  # no void ratio, or one outside the map (check_density's)
        try:
            opening_spread.check(alpha0, args.alpha0_spread)
        except ValueError as exc:
            raise UserError(f"--alpha0-spread at {test.name}'s void ratio {test.void_ratio:g} (the map's "
                            f"alpha0): {exc}") from None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    tests = read_tests(args.data)
    check_args(args, tests)
    try:
        prior = bayes.make_prior(args.params, args.prior, dim=max(t.dim for t in tests), law=args.law)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    settings = with_density(forward_settings(args, max(t.dim for t in tests)), tests, args.e_min, args.e_max)
    check_rule_prior(prior, settings)
    check_interlocking_prior(prior, settings)
    check_start_scales(args, prior)
    try:
        check_density(tests, args.params, settings, dict(zip(prior.names, zip(prior.low, prior.high))))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_spread_at_void_ratios(args, tests, settings)
    check_out(args.out, args.overwrite)
    config = configuration(args, tests, prior, settings)
    started = time.perf_counter()
    from homogenization.calibration import report  # noqa: PLC0415 (matplotlib: only once the input is good)

    with output_lock(args.out):
        result = run_calibration(args, tests, prior, settings, config)
    say(*report.summary_lines(result), f"{args.out}: done in {time.perf_counter() - started:.0f} s")
    for warning in report.warnings(result):
        print(f"hmodel calibrate: {warning}", file=sys.stderr)
    return 0


def stored_chain(chain: Path, overwrite: bool) -> tuple[str | None, int]:
    """The settings (``calibration_config``; None: none recorded) and the steps of the chain file ``chain``; (None, 0)
    where there is none, or an unreadable one and ``overwrite``.

    Raises:
        UserError: an unreadable chain without ``overwrite``."""
    import emcee  # noqa: PLC0415
    import h5py  # noqa: PLC0415

    if not chain.exists():
        return None, 0
    try:
        with h5py.File(chain, "r") as fh:
            stored = fh.attrs.get("calibration_config")
        return stored, int(emcee.backends.HDFBackend(str(chain), read_only=True).iteration)
    except (OSError, KeyError):
        if overwrite:
            return None, 0
        raise UserError(f"{chain} is unreadable (a run killed while writing it?); add --overwrite to restart "
                        f"the chain") from None


def run_calibration(args: argparse.Namespace, tests: Sequence[Measurement], prior: bayes.Prior,
                    settings: ForwardSettings, config: dict[str, Any]) -> dict[str, Any]:
    """Sample (resuming chain.h5 where it matches ``config``), then write every output."""
    import emcee  # noqa: PLC0415 (only when a calibration runs)
    import h5py  # noqa: PLC0415

    from homogenization.calibration import report  # noqa: PLC0415

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    chain = out / CHAIN_FILE
    config_json = json.dumps(config, sort_keys=True)
    stored, done = stored_chain(chain, args.overwrite)
    if done and stored != config_json and not args.overwrite:
        raise UserError(f"{chain} holds a calibration with other settings (data, parameters, prior, walkers, "
                        f"moves, seed or forward model); add --overwrite to restart it")
    if done > args.steps and not args.overwrite:  # --steps is the total, as emcee's backend keeps every step
        raise UserError(f"{chain} already holds {done} steps, more than --steps {args.steps}; pass --steps {done} to "
                        f"report on them (more extends the chain), or add --overwrite to restart it with {args.steps}")
    restart = args.overwrite or not done or stored != config_json
    log_post = bayes.Posterior(tests, prior, settings, likelihood_noise(args), workers=args.workers)
    try:
        started = time.perf_counter()
        n_dim = len(prior.names)
        if restart:  # the start first: a refused or interrupted one leaves the folder as it was
            start, start_record, resolution_record = resolved_start(args, log_post)
            start_record["seconds"] = time.perf_counter() - started
            start_record["forward_counts"] = report.forward_counts(log_post.take_counts(), start=True)
            for name in (CHAIN_FILE, *report.OUTPUT_FILES):
                (out / name).unlink(missing_ok=True)
            backend = emcee.backends.HDFBackend(str(chain))
            backend.reset(args.walkers, n_dim)
            with h5py.File(chain, "a") as fh:
                fh.attrs["calibration_config"] = config_json
                fh.attrs["start_record"] = json.dumps(start_record, sort_keys=True)
                fh.attrs["resolution_record"] = json.dumps(resolution_record, sort_keys=True)
            done = 0
        else:
            backend = emcee.backends.HDFBackend(str(chain))
            start = backend.get_last_sample()  # positions, log posterior and random state of the last step
            with h5py.File(chain, "r") as fh:
                stored_start = fh.attrs.get("start_record")
                stored_resolution = fh.attrs.get("resolution_record")
                log_post.add_counts(json.loads(fh.attrs.get("forward_counts", "{}")))  # the earlier processes'
            start_record = json.loads(stored_start) if stored_start is not None else None
            resolution_record = json.loads(stored_resolution) if stored_resolution is not None else {"mode": "off"}
            if resolution_record.get("correction") is not None:
                log_post.correction = [{c: np.asarray(v) for c, v in t.items()}
                                       for t in resolution_record["correction"]]
            say(f"{chain}: resuming after {done} of {args.steps} steps")
        sampler = emcee.EnsembleSampler(args.walkers, n_dim, log_post, moves=bayes.sampler_moves(args.moves),
                                        vectorize=True, backend=backend)
        # emcee's wrapper of log_post prints a traceback of any exception, Ctrl-C included, before
        # passing it on; run_main reports it in one line instead (the chain keeps every finished step)
        sampler.log_prob_fn = log_post
        if restart:
            sampler.random_state = np.random.RandomState(args.seed).get_state()
        seconds = time.perf_counter()
        remaining = max(0, args.steps - done)
        if remaining:
            # emcee's acceptance of a walker at -inf (a failed forward run) is nan; failures are counted and reported
            with progress_bar(total=remaining, desc="calibrate", unit="step") as bar, np.errstate(invalid="ignore"):
                for _ in sampler.sample(start, iterations=remaining):
                    with h5py.File(chain, "a") as fh:  # the counts so far, for a resumed run to add to
                        fh.attrs["forward_counts"] = json.dumps(log_post.counts())
                    bar.update(1)
        seconds = time.perf_counter() - seconds
        return report.write_outputs(out, sampler, log_post, args, seconds, config, start_record, resolution_record)
    finally:
        log_post.close()  # its worker processes, if any


RULE_FLAGS = {2: lambda ref: f"--orientations {ref.n_orientations}",
              3: lambda ref: f"--order {ref.lebedev_order} --spins {ref.n_spins}"}
"""The flags of a forward model's orientation rule (``ForwardSettings``) by the data's dimension."""


def resolved_start(args: argparse.Namespace, log_post: bayes.Posterior) -> tuple[np.ndarray, dict, dict]:
    """The walkers' start (--start) with the forward model's resolution checked there (--resolution): where
    its discretisation error is not well below the noise, ``resolution.reference`` finds a finer model
    (each refinement reported), its difference at the start point is added to every curve
    (``log_post.correction``, set in place) and the start is found again (--start map: one fit from the
    previous optimum; recorded in the resolution's ``starts_after_correction``), at most ``RESOLUTION_RESTARTS`` times. Returns the walkers, the start's record and the resolution's record.

    Raises:
        UserError: --resolution check and a model too coarse, or no reference within
            ``resolution.MAX_REFINEMENTS`` refinements (one line naming the flags to set).
    """
    from homogenization.calibration import report, resolution  # noqa: PLC0415

    record: dict[str, Any] = {"mode": args.resolution, "restarts": 0, "correction": None}
    if args.start_point is not None:  # --start map from the given values: one fit (one per --start-scales factor)
        given = np.array([args.start_point[n] for n in log_post.prior.names])
        if args.start_scales is not None:
            name, factors = args.start_scales
            given = np.repeat(given[None, :], len(factors), axis=0)
            given[:, log_post.prior.names.index(name)] *= factors
        start, start_record = refit_start(log_post, log_post.prior.to_coord(given), args.walkers,
                                          np.random.default_rng(args.seed))
    else:
        start, start_record = START_METHODS[args.start](log_post, args.walkers, np.random.default_rng(args.seed))
    say(report.start_line(start_record))
    if args.resolution == "off":
        return start, start_record, record
    x = start_point(log_post, start, start_record)
    try:
        ref, levels = resolution.reference(log_post, x)
    except resolution.ResolutionError as exc:
        raise UserError(f"the forward model is still too coarse for these data after {resolution.MAX_REFINEMENTS} "
                        f"refinements ({exc}); give finer --increment and --orientations (2D) or --order and --spins "
                        f"(3D), or --model-error, or --resolution off") from None
    for level in levels:
        say(level.line())
    record.update(levels=[level.to_dict() for level in levels], reference=resolution.knob_settings(ref),
                  refinements=len(levels) - 1)
    if len(levels) == 1:
        return start, start_record, record
    if args.resolution == "check":
        rule = RULE_FLAGS[max(t.dim for t in log_post.tests)](ref)
        raise UserError(f"the forward model's discretisation error is not well below the noise ({levels[0].line()}); "
                        f"set --increment {ref.increment:g} --iso-increment {ref.iso_increment:g} {rule}, or "
                        f"--resolution correct")
    checks = []
    for restart in range(1, RESOLUTION_RESTARTS + 1):
        log_post.correction = resolution.correction(log_post, ref, x)
        rng = np.random.default_rng(args.seed)
        start, again = (refit_start(log_post, x, args.walkers, rng) if args.start == "map" else
                        START_METHODS[args.start](log_post, args.walkers, rng))
        say(f"forward model corrected by the reference's difference at {format_point(log_post, x)}; "
            + report.start_line(again))
        x_new = start_point(log_post, start, again)
        record.setdefault("starts_after_correction", []).append(again)
        checks.append(resolution.check(log_post, x_new, "start", against=ref))
        say(checks[-1].line())
        record["restarts"] = restart
        x_done, x = x, x_new
        if checks[-1].passed:
            break
    record.update(correction=[{c: v.tolist() for c, v in t.items()} for t in log_post.correction],
                  corrected_at=dict(zip(log_post.prior.names, log_post.prior.to_values(x_done).tolist())),
                  start_checks=[c.to_dict() for c in checks])
    return start, start_record, record


RESOLUTION_RESTARTS = 2
"""Starts found again after a discretisation correction, at most [-]."""


def start_point(log_post: bayes.Posterior, walkers: np.ndarray, record: dict) -> np.ndarray:
    """Where the start's resolution is checked: the least-squares optimum (--start map) or the best walker."""
    if "optimum" in record:
        return log_post.prior.to_coord(np.array([record["optimum"][n] for n in log_post.prior.names]))
    with np.errstate(all="ignore"):
        return walkers[int(np.argmax(log_post(walkers)))]


def format_point(log_post: bayes.Posterior, x: np.ndarray) -> str:
    """"phi_g 26.5, alpha0 52.5" of sampled coordinates x."""
    return ", ".join(f"{n} {v:.4g}" for n, v in zip(log_post.prior.names, log_post.prior.to_values(x)))
