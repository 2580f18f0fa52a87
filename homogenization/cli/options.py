"""Options shared by the commands of ``homogenization.cli``: the parser, the cell and the backend.

- ``command_parser(module, description)``: the parser of a command, named as the user typed
  it, with the flags every command shares and its defaults shown (``warp_hcell.core.cli``);
- ``backend_list`` and ``add_backend_argument(parser)``: --backend, one of the registry's names;
  ``add_backend_list_argument(parser, default, note)``: a comma list of them, overlaid;
- ``add_programme_arguments(parser, ...)``: the group of a built-in programme (--p0, --eps-max,
  --increment, --iso-increment), not with --programme;
- ``add_alpha0_argument(parser)``: --alpha0 [deg], the opening angle of builder specs;
  ``add_void_ratio_arguments(parser)``: --void-ratio E and the map's --e-min, --e-max
  (``homogenization.material.density``), resolved by ``run_files.resolve_void_ratio``;
- ``add_cell_arguments(parser, cell_help, threads_help)``: --mesostructure (a file or a
  builder spec), --threads and --model (the backend-specific options);
- ``add_orientations_argument(parser, default, help_text)`` and ``add_threads_argument(parser,
  help_text, default)``: --orientations and --threads, the flags of that name of every command;
  ``add_spatial_rule_arguments(parser, order, spins)``: --order and --spins, the orientations of
  3D cells (``lebedev_order`` checks the order);
- ``add_uncertified_argument(parser)`` and ``refuse_uncertified(model, args)``: --uncertified-ok,
  and the refusal (one line, exit 2) of an ANN model without a passed certificate of its own
  ``.pt`` (docs/certificate.md); ``certificate_note(model)`` is the line a run summary prints;
- ``EXIT_CODES_HELP``: the --help epilog of the commands that end with a certificate;
- ``add_posterior_arguments(parser)``: --posterior (run at a calibration's posterior mean) and
  --posterior-band N (the 95 % band of N posterior draws), applied by ``homogenization.cli.posterior_flags``;
- ``add_active_arguments(parser)``: the budget of the active-learning rounds (--rounds,
  --samples-per-round, --max-samples, --max-seconds, --warm-start, --widen; defaults from
  ``homogenization.learning.settings.ActiveSettings``) and the certificate's --orientations (planar cells),
  --order and --spins (spatial cells) and --eps-max,
  read back with ``active_settings(args)`` and ``certificate_settings(args)`` (``hmodel learn`` and
  ``hmodel train``);
- ``add_certificate_equilibrium_arguments(parser)``: --equilibrium-corrections K and --equilibrium-tolerance R
  of the certificate's ANN runs (the hybrid; ``hmodel certify``, ``hmodel train``, ``hmodel learn``), read
  back with ``certificate_settings(args, meso)`` (without the flag: the cell's default,
  ``homogenization.learning.settings.default_equilibrium``); ``equilibrium_line`` says it.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from homogenization.backends import BACKENDS
from homogenization.material.density import DEFAULT_E_MAX, DEFAULT_E_MIN, OPENING_RANGE_DEG
from homogenization.learning.settings import (ActiveSettings, CertificateSettings, default_equilibrium, RELEASE_RULE_NAMES,
                                              FINES_EQUILIBRIUM_CORRECTIONS, FINES_EQUILIBRIUM_TOLERANCE)
from warp_hcell.core.cli import UserError, alpha0_deg, axial_strain, command_parser, int_at_least, non_negative_float, positive_float, positive_int  # noqa: F401 (command_parser: the commands import it from here)
from warp_hcell.core.parameters import CellDefaults, DemSettings, LoadingDefaults
from warp_hcell.mesostructures.builders import MESOSTRUCTURE_HELP, mesostructure_arg

EXIT_CODES_HELP = ("exit codes: 0 the certificate passed; 2 bad input (one line, before any work); 3 the certificate "
                   "failed (worst > target); 4 within the target but below the minimum certificate "
                   "(homogenization.ann.envelope.MINIMUM), so not passed; 130 interrupted (docs/usage.md, Failures and existing output)")
"""The --help epilog of the commands that end with a certificate (certify, train, learn;
``homogenization.learning.certificate.exit_code``)."""
ISO_TO_SHEAR_INCREMENT = LoadingDefaults.iso_increment / LoadingDefaults.increment
"""Default --iso-increment as a fraction of --increment (5e-6 / 1e-5 = 0.5)."""


def backend_list(text: str) -> tuple[str, ...]:
    """argparse type: comma list of registered backend names (duplicates dropped, order kept)."""
    names = tuple(dict.fromkeys(name.strip() for name in text.split(",")))
    for name in names:
        if name not in BACKENDS:
            raise argparse.ArgumentTypeError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
    return names


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """--backend, one cell model of ``homogenization.backends.BACKENDS`` (default analytical)."""
    parser.add_argument("--backend", choices=tuple(BACKENDS), default="analytical", help="cell model")


def add_backend_list_argument(parser: argparse.ArgumentParser, default: str | tuple[str, ...], note: str = "") -> None:
    """--backend, a ``backend_list`` whose runs are overlaid; ``note`` ends its help."""
    parser.add_argument("--backend", type=backend_list, default=default,
                        help=f"cell model, or a comma list to overlay several; choices: {', '.join(BACKENDS)}{note}")


def add_programme_arguments(parser: argparse.ArgumentParser, *, stress_unit: str, eps_max: float, eps_max_help: str,
                            increment: float) -> argparse._ArgumentGroup:
    """The group "built-in programme (not with --programme)": --p0 [``stress_unit``], --eps-max
    (default ``eps_max``), --increment (default ``increment``) and --iso-increment (default: not
    set, read as ``ISO_TO_SHEAR_INCREMENT`` x --increment by ``run_files.shear_iso_increment``).

    Returns:
        The group, for the command's own flags of the built-in programme.
    """
    group = parser.add_argument_group("built-in programme (not with --programme)")
    group.add_argument("--p0", type=positive_float, default=CellDefaults.p0,
                       help=f"confining pressure of stage 1 [{stress_unit}], > 0")
    group.add_argument("--eps-max", type=axial_strain, default=eps_max, help=eps_max_help)
    group.add_argument("--increment", type=positive_float, default=increment,
                       help="axial strain increment of the shear stage [-], <= --eps-max")
    group.add_argument("--iso-increment", type=positive_float, default=argparse.SUPPRESS,
                       help=f"strain increment per component of the isotropic stage [-] "
                            f"(default: {ISO_TO_SHEAR_INCREMENT:g} x --increment)")
    return group


def add_alpha0_argument(parser: argparse.ArgumentParser) -> None:
    """--alpha0 [deg] in [30, 90) (default ``CellDefaults.alpha0_deg``)."""
    parser.add_argument("--alpha0", type=alpha0_deg, default=CellDefaults.alpha0_deg,
                        help="initial opening angle [deg], in [30, 90)")


def void_ratio_value(text: str) -> float:
    """argparse type: a void ratio [-], a finite float >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (value == value and abs(value) != float("inf") and value >= 0.0):
        raise argparse.ArgumentTypeError(f"{text}: a void ratio is a finite number >= 0")
    return value


def add_void_ratio_arguments(parser: argparse.ArgumentParser) -> None:
    """The group "density": --void-ratio E (default None: the cell of --alpha0) and the void-ratio map's
    --e-min and --e-max [-] (defaults ``density.DEFAULT_E_MIN``, ``DEFAULT_E_MAX``)."""
    angles = "; ".join(f"{d}D {a:g}-{b:g} deg" for d, (a, b) in OPENING_RANGE_DEG.items())
    group = parser.add_argument_group(f"density (instead of --alpha0): alpha0 linear in e between the densest and "
                                      f"the loosest cell ({angles}; docs/usage.md, Density)")
    group.add_argument("--void-ratio", type=void_ratio_value, default=None, metavar="E",
                       help="initial void ratio e0 [-] of the cells, in [--e-min, --e-max]; not with --alpha0")
    group.add_argument("--e-min", type=void_ratio_value, default=DEFAULT_E_MIN,
                       help="void ratio of the densest cell [-] (with --void-ratio)")
    group.add_argument("--e-max", type=void_ratio_value, default=DEFAULT_E_MAX,
                       help="void ratio of the loosest cell [-] (with --void-ratio)")


RENEWAL_PHASES = ("cell", "axis", "mirror", "mirror-spin")
"""The choices of --renewal-phases (``homogenization.material.critical_state.PHASES``)."""


def add_critical_state_argument(parser: argparse.ArgumentParser) -> None:
    """--critical-state: renew the cells towards a critical state (opt-in; off: the plain H-model); --renewal-phases:
    which cells its rule renews together (None: the rule's default)."""
    parser.add_argument("--critical-state", action="store_true",
                        help="renew the cells between increments towards a critical state, with the measured "
                             "parameters of the cells' dimension (docs/usage.md, Critical state)")
    parser.add_argument("--renewal-phases", choices=RENEWAL_PHASES, default=None,
                        help="with --critical-state: the cells renewed together (default cell: mirror-image cells; "
                             "docs/usage.md, Critical state)")


def critical_state_rule(dim: int, phases: str | None = None):
    """The ``CriticalState`` that --critical-state runs with cells of dimension ``dim``: its ``DEFAULTS``, with
    ``phases`` (--renewal-phases) where given."""
    from dataclasses import replace  # noqa: PLC0415
    from homogenization.material.critical_state import DEFAULTS  # noqa: PLC0415 (only runs that ask for it)
    return DEFAULTS[dim] if phases is None else replace(DEFAULTS[dim], phases=phases)


def add_orientations_argument(parser: argparse.ArgumentParser, default: int,
                              help_text: str = "number N of cell orientations") -> None:
    """--orientations: the number N of cell orientations [-], a positive int (default ``default``)."""
    parser.add_argument("--orientations", type=positive_int, default=default, help=help_text)


def lebedev_order(text: str) -> int:
    """argparse type: one of ``orientation.LEBEDEV_ORDERS``."""
    from homogenization.material.orientation import LEBEDEV_ORDERS  # noqa: PLC0415 (scipy: only the commands of 3D cells)

    order = positive_int(text)
    if order not in LEBEDEV_ORDERS:
        raise argparse.ArgumentTypeError(f"Lebedev order {order} is not one of {', '.join(map(str, LEBEDEV_ORDERS))}")
    return order


def add_spatial_rule_arguments(parser: argparse.ArgumentParser, order: int, spins: int, what: str = "") -> None:
    """--order and --spins: the orientations of 3D cells, a Lebedev rule on the hemisphere of that
    order times that many spins about each axis (defaults ``order``, ``spins``)."""
    parser.add_argument("--order", type=lebedev_order, default=order,
                        help=f"Lebedev order of the cell axes of 3D cells{what}")
    parser.add_argument("--spins", type=positive_int, default=spins, help=f"spins of each 3D cell about its axis{what}")


def add_threads_argument(parser: argparse.ArgumentParser, help_text: str, default: int | None = None) -> None:
    """--threads: CPU threads, a positive int (default ``default``; None: the backend's own)."""
    parser.add_argument("--threads", type=positive_int, default=default, help=help_text)


def add_cell_arguments(parser: argparse.ArgumentParser, cell_help: str, threads_help: str) -> None:
    """--mesostructure (``cell_help`` then the spec grammar), --threads and --model."""
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None, help=f"{cell_help} {MESOSTRUCTURE_HELP}")
    add_threads_argument(parser, threads_help)
    parser.add_argument("--model", type=Path, default=None, help="ANN checkpoint (ann only; None: the installed model)")


CHECKPOINT_SECONDS = 60.0
"""Default wall time [s] between two checkpoints of a run command (``--checkpoint-seconds``)."""


def add_checkpoint_arguments(parser: argparse.ArgumentParser) -> None:
    """--checkpoint-seconds and --restart of the run commands (``run_files.run_checkpoints``)."""
    group = parser.add_argument_group("interruption and resume")
    group.add_argument("--checkpoint-seconds", type=non_negative_float, default=CHECKPOINT_SECONDS, metavar="S",
                       help="save the run's state every S s of wall time (0: after every increment, each save "
                            "writing the whole state and history) in .OUT.resume "
                            "next to --out; the same command run again after an interruption resumes from it and "
                            "gives the uninterrupted run's result")
    group.add_argument("--restart", action="store_true",
                       help="discard the checkpoint of an interrupted run on --out and start from the first increment")


def add_uncertified_argument(parser: argparse.ArgumentParser) -> None:
    """--uncertified-ok: run an ANN model that is uncertified, failed its certificate, or whose
    certificate was measured on another file."""
    parser.add_argument("--uncertified-ok", action="store_true",
                        help="ann: run a model without a passed certificate of this very file (docs/certificate.md)")


def refuse_uncertified(model: object, args: argparse.Namespace) -> None:
    """UserError (one line) if ``model`` is an ANN backend whose ``certificate_problem`` is set
    and the user did not pass --uncertified-ok; other backends pass."""
    problem = getattr(model, "certificate_problem", None)
    if problem is not None and not getattr(args, "uncertified_ok", False):
        raise UserError(f"ann: {problem}; pass --uncertified-ok to run it anyway")


def refuse_uncertified_file(path: Path | None, args: argparse.Namespace) -> None:
    """``refuse_uncertified`` for a model file not built here (e.g. built by sweep workers):
    ``path`` None is the installed model; a missing file is left to the backend to report."""
    from homogenization.ann import default_model_path  # noqa: PLC0415
    from homogenization.ann.policy import certificate_problem  # noqa: PLC0415 (Warp)
    from training.checkpoint import read_metadata  # noqa: PLC0415

    path = default_model_path() if path is None else Path(path)
    if path.is_file() and not getattr(args, "uncertified_ok", False):
        problem = certificate_problem(read_metadata(path), path)
        if problem is not None:
            raise UserError(f"ann: {problem}; pass --uncertified-ok to run it anyway")


def certificate_note(model: object) -> str:
    """Summary text of an ANN backend's certificate ('' for other backends)."""
    if not hasattr(model, "certificate_problem"):
        return ""
    cert = model.certificate
    if model.certificate_problem is None:
        return f", certificate passed (worst {100 * cert.worst:.3g} % of the scale)"
    problem = model.certificate_problem
    worst = (f", worst {100 * cert.worst:.3g} %" if cert is not None and "worst" not in problem
             else "")
    return f", UNCERTIFIED ({problem.split(': ', 1)[-1]}{worst}; --uncertified-ok)"


def add_posterior_arguments(parser: argparse.ArgumentParser) -> None:
    """The group "calibrated micro-parameters": --posterior (posterior.json of ``hmodel calibrate``,
    or its folder) and --posterior-band N (a positive int; None: no band)."""
    group = parser.add_argument_group("calibrated micro-parameters")
    group.add_argument("--posterior", type=Path, default=None,
                       help="posterior.json of hmodel calibrate (or its folder): run at the posterior mean of its "
                            "parameters (phi_g, kn, kt/kn, alpha0, radius; not with --phi, --kn, --kt, --alpha0, "
                            "--radius, --mesostructure)")
    group.add_argument("--posterior-band", type=positive_int, default=None, metavar="N",
                       help="also draw N parameter sets from the posterior's samples and write the 95 %% band of q, "
                            "p and eps_v over eps1 (posterior_band.csv, in the figure); built-in drained or "
                            "undrained tests only")


def add_active_arguments(parser: argparse.ArgumentParser) -> None:
    """The budget of the active-learning rounds (defaults ``ActiveSettings``) and the
    certificate's --orientations, --order, --spins and --eps-max (defaults ``CertificateSettings``:
    the minimum certificate)."""
    budget, measured = ActiveSettings(), CertificateSettings()
    parser.add_argument("--rounds", type=int, default=budget.rounds, help="active-learning rounds at most (0: none)")
    parser.add_argument("--samples-per-round", type=positive_int, default=budget.samples_per_round,
                        help="samples added per round")
    parser.add_argument("--max-samples", type=positive_int, default=budget.max_samples,
                        help="samples added over all rounds at most")
    parser.add_argument("--max-seconds", type=positive_float, default=budget.max_seconds,
                        help="wall time [s] after which no new round starts (a resumed run counts its earlier rounds' time)")
    parser.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=budget.warm_start,
                        help="retrain each round from the previous round's weights")
    parser.add_argument("--widen", action=argparse.BooleanOptionalAction, default=budget.widen,
                        help="let a round that gained little give the next a wider network (WIDTH_LADDER)")
    parser.add_argument("--max-database-mb", type=positive_float, default=budget.max_database_mb,
                        help="size budget of the database file [MB]: a round adds only the samples that fit")
    parser.add_argument("--stall-rounds", type=positive_int, default=budget.stall_rounds,
                        help="rounds in a row without progress after which the rounds stop with a diagnosis")
    parser.add_argument("--round-target", type=positive_float, default=None, metavar="F",
                        help="the rounds go on until the worst test is within this fraction of its scale, stricter "
                             f"than the certificate's target {measured.target:g} (whose verdict is unchanged); "
                             "default: that target")
    parser.add_argument("--departure-margin", type=float, default=budget.departure_margin,
                        help="fraction of a failing test's increments before its point of departure whose "
                             "DEM states are probed with those after it (1: every state of the test)")
    add_orientations_argument(parser, measured.n_orientations, "cell orientations per certificate test (planar cells)")
    add_spatial_rule_arguments(parser, *measured.spatial_rule, " in the certificate's tests")
    parser.add_argument("--eps-max", type=axial_strain, default=measured.eps_max,
                        help="axial strain of each certificate shear stage [-]")
    add_certificate_equilibrium_arguments(parser)


correction_count = int_at_least(0)
"""argparse type of --equilibrium-corrections: an integer >= 0 (0: the network alone)."""


def add_equilibrium_arguments(parser: argparse.ArgumentParser, corrections_help: str) -> None:
    """--equilibrium-corrections K (``corrections_help`` says what K does for the command and what
    it is when not given) and --equilibrium-tolerance R of the hybrid meso-ANN (docs/ann.md,
    "Equilibrium corrections")."""
    parser.add_argument("--equilibrium-corrections", type=correction_count, default=None, metavar="K",
                        help=corrections_help)
    parser.add_argument("--equilibrium-tolerance", type=positive_float, default=None, metavar="R",
                        help="with --equilibrium-corrections: the force ratio above which a cell is corrected "
                             "(None: the DEM's force tolerance, 1e-6)")


def add_certificate_equilibrium_arguments(parser: argparse.ArgumentParser) -> None:
    """--equilibrium-corrections K, --equilibrium-tolerance R and --release-rule of the certificate's ANN runs
    (``CertificateSettings``; default: ``settings.default_equilibrium`` of the cell, rule ``resting``)."""
    add_equilibrium_arguments(parser, "certify the hybrid: the tests run the ANN with up to K exact Newton steps on "
                                      "the free grains' balance after the network's step (spatial cells; "
                                      "docs/certificate.md); runs are then certified with this K and tolerance only. "
                                      f"None: K = {FINES_EQUILIBRIUM_CORRECTIONS} at tolerance "
                                      f"{FINES_EQUILIBRIUM_TOLERANCE:g} for a 3D cell with fine grains, 0 (the "
                                      "network alone) for any other; 0: the network alone")
    parser.add_argument("--release-rule", choices=RELEASE_RULE_NAMES, default=RELEASE_RULE_NAMES[0],
                        help="the hybrid's rule for the free grains nothing presses (homogenization.ann.escalation): "
                             "'resting' (RELEASE_RULE, the default) or 'drag' (RELEASE_RULE_DRAG: a lightly pushed "
                             "grain also relaxed as the DEM does from rest); recorded, and runs of the other rule "
                             "are not covered")


def active_settings(args: argparse.Namespace) -> ActiveSettings:
    """The ``ActiveSettings`` of the flags of ``add_active_arguments`` (UserError, one line, if invalid)."""
    target = CertificateSettings().target
    if args.round_target is not None and args.round_target > target:
        raise UserError(f"--round-target {args.round_target:g}: above the certificate's target {target:g}; "
                        f"give a stricter aim or leave it out")
    try:
        return ActiveSettings(rounds=args.rounds, samples_per_round=args.samples_per_round,
                              max_samples=args.max_samples, max_seconds=args.max_seconds,
                              warm_start=args.warm_start, widen=args.widen, max_database_mb=args.max_database_mb,
                              stall_rounds=args.stall_rounds, departure_margin=args.departure_margin,
                              round_target=args.round_target)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def certificate_settings(args: argparse.Namespace, meso: Any = None) -> CertificateSettings:
    """The ``CertificateSettings`` of the flags of ``add_active_arguments`` and --no-rollout
    (UserError, one line: --equilibrium-tolerance without --equilibrium-corrections, or with 0; --release-rule
    drag for the network alone).
    Without --equilibrium-corrections the cell's default surrogate (``settings.default_equilibrium``
    of ``meso``, the ``Mesostructure`` of the model; None: the network alone)."""
    if args.equilibrium_tolerance is not None and args.equilibrium_corrections is None:
        raise UserError("--equilibrium-tolerance applies with --equilibrium-corrections only")
    if args.equilibrium_corrections is None:
        corrections, tolerance = (0, None) if meso is None else default_equilibrium(meso)
    else:
        corrections, tolerance = args.equilibrium_corrections, args.equilibrium_tolerance
    # without the cell, a rule other than the default can be checked against an explicit K only
    rule = args.release_rule if meso is not None or args.equilibrium_corrections is not None else "resting"
    if rule != "resting" and not corrections:
        raise UserError(f"--release-rule {rule}: a rule of the hybrid; these tests run the network alone "
                        f"(--equilibrium-corrections 0, or a cell without fine grains)")
    try:
        return CertificateSettings(n_orientations=args.orientations, spatial_rule=(args.order, args.spins),
                                   eps_max=args.eps_max, rollout=not args.no_rollout,
                                   equilibrium_corrections=corrections, equilibrium_tolerance=tolerance,
                                   release_rule=rule)
    except ValueError as exc:
        raise UserError(f"--equilibrium-corrections / --equilibrium-tolerance / --release-rule: {exc}") from None


def equilibrium_line(measured: CertificateSettings, explicit: bool) -> str:
    """The line that says which surrogate a command certifies: ``measured``'s K and tolerance, and
    whether the cell's default (``explicit`` False) or the flags chose it."""
    k, tolerance = measured.equilibrium_corrections, measured.equilibrium_tolerance
    which = "--equilibrium-corrections" if explicit else "the default of this cell"
    if not k:
        return f"certified surrogate: the network alone ({which})"
    return (f"certified surrogate: the network with up to {k} equilibrium corrections at force ratio "
            f"{tolerance if tolerance is not None else DemSettings().force_tolerance:g} ({which}; "
            f"--equilibrium-corrections 0: the network alone)")
