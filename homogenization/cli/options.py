"""Options shared by the commands of ``homogenization.cli``: the parser, the cell and the backend.

- ``command_parser(module, description)``: the parser of a command, named as the user typed
  it, with the flags every command shares and its defaults shown (``warp_hcell.core.cli``);
- ``add_backend_argument(parser)``: --backend, one of the registry's names;
- ``add_alpha0_argument(parser)``: --alpha0 [deg], the opening angle of builder specs;
- ``add_cell_arguments(parser, cell_help, threads_help)``: --mesostructure (a file or a
  builder spec), --threads and --model (the backend-specific options);
- ``add_uncertified_argument(parser)`` and ``refuse_uncertified(model, args)``: --uncertified-ok,
  and the refusal (one line, exit 2) of an ANN model without a passed certificate of its own
  ``.pt`` (docs/certificate.md); ``certificate_note(model)`` is the line a run summary prints;
- ``add_active_arguments(parser)``: the budget of the active-learning rounds (--rounds,
  --samples-per-round, --max-samples, --max-seconds, --warm-start, --widen; defaults from
  ``homogenization.active.ActiveSettings``) and the certificate's --orientations and --eps-max,
  read back with ``active_settings(args)`` and ``certify_options(args)`` (``hmodel learn`` and
  ``hmodel train``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from homogenization.backends import BACKENDS
from warp_hcell.core.cli import UserError, alpha0_deg, command_parser, positive_float, positive_int  # noqa: F401 (command_parser: the commands import it from here)
from warp_hcell.core.parameters import CellDefaults
from warp_hcell.mesostructures.builders import MESOSTRUCTURE_HELP, mesostructure_arg


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """--backend, one cell model of ``homogenization.backends.BACKENDS`` (default analytical)."""
    parser.add_argument("--backend", choices=tuple(BACKENDS), default="analytical", help="cell model")


def add_alpha0_argument(parser: argparse.ArgumentParser) -> None:
    """--alpha0 [deg] in [30, 90) (default ``CellDefaults.alpha0_deg``)."""
    parser.add_argument("--alpha0", type=alpha0_deg, default=CellDefaults.alpha0_deg,
                        help="initial opening angle [deg], in [30, 90)")


def add_cell_arguments(parser: argparse.ArgumentParser, cell_help: str, threads_help: str) -> None:
    """--mesostructure (``cell_help`` then the spec grammar), --threads and --model."""
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None, help=f"{cell_help} {MESOSTRUCTURE_HELP}")
    parser.add_argument("--threads", type=positive_int, default=None, help=threads_help)
    parser.add_argument("--model", type=Path, default=None, help="ANN checkpoint (ann only; None: the installed model)")


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
    from homogenization.backends.ann import certificate_problem, default_model_path  # noqa: PLC0415 (torch)
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
        return f", certificate passed (worst {100 * cert['worst']:.3g} % of the scale)"
    problem = model.certificate_problem
    worst = (f", worst {100 * cert['worst']:.3g} %" if isinstance(cert, dict) and "worst" in cert and "worst" not in problem
             else "")
    return f", UNCERTIFIED ({problem.split(': ', 1)[-1]}{worst}; --uncertified-ok)"


def add_active_arguments(parser: argparse.ArgumentParser) -> None:
    """The budget of the active-learning rounds (defaults ``ActiveSettings``) and the
    certificate's --orientations and --eps-max (defaults ``homogenization.certificate``)."""
    from homogenization import active, certificate  # noqa: PLC0415 (torch: only the commands that learn)

    budget = active.ActiveSettings()
    parser.add_argument("--rounds", type=int, default=budget.rounds, help="active-learning rounds at most (0: none)")
    parser.add_argument("--samples-per-round", type=positive_int, default=budget.samples_per_round,
                        help="samples added per round")
    parser.add_argument("--max-samples", type=positive_int, default=budget.max_samples,
                        help="samples added over all rounds at most")
    parser.add_argument("--max-seconds", type=positive_float, default=budget.max_seconds,
                        help="wall time [s] after which no new round starts")
    parser.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=budget.warm_start,
                        help="retrain each round from the previous round's weights")
    parser.add_argument("--widen", action=argparse.BooleanOptionalAction, default=budget.widen,
                        help="let a round that gained little give the next a wider network (WIDTH_LADDER)")
    parser.add_argument("--orientations", type=positive_int, default=certificate.N_ORIENTATIONS,
                        help="cell orientations per certificate test")
    parser.add_argument("--eps-max", type=positive_float, default=certificate.EPS_MAX,
                        help="axial strain of each certificate shear stage [-]")


def active_settings(args: argparse.Namespace):
    """The ``ActiveSettings`` of the flags of ``add_active_arguments`` (UserError, one line, if invalid)."""
    from homogenization import active  # noqa: PLC0415

    try:
        return active.ActiveSettings(rounds=args.rounds, samples_per_round=args.samples_per_round,
                                     max_samples=args.max_samples, max_seconds=args.max_seconds,
                                     warm_start=args.warm_start, widen=args.widen)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def certify_options(args: argparse.Namespace) -> dict[str, Any]:
    """``certificate.certify`` keywords of the flags of ``add_active_arguments`` and --no-rollout."""
    return {"n_orientations": args.orientations, "eps_max": args.eps_max, "rollout": not args.no_rollout}
