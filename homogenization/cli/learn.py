"""hmodel learn --mesostructure FILE|SPEC --out DIR [--samples N] [--rounds R] [--seed S]

(also ``python -m homogenization.learn``.) The whole pipeline of one mesostructure, each stage
skipped when its output is complete (a second call continues; an interrupted stage restarts):

1. ``DIR/db.h5``: the learning database (``warp_hcell.database.generate``; resumes from its
   sidecar ``DIR/db.h5.parts``);
2. ``DIR/ann.pt``, ``DIR/ann.json``: the meso-ANN (``training.train``), skipped when the JSON's
   training data is the current ``db.h5`` or it is the kept model of earlier rounds on it;
3. the certificate and the active-learning rounds (``homogenization.learning.active.learn``): while the
   certificate fails, the budget (``ActiveSettings``: rounds, samples, seconds, the database's
   size) is left and rounds make progress, the DEM states of the failing tests are probed,
   appended to ``db.h5`` and the model is retrained (from scratch, or from the kept weights with --warm-start);
4. ``DIR/certificate.png``: p and q of the ANN and the DEM on the certificate's worst test.

``DIR/learn.json`` records the options of the run (the certified surrogate, --order, --spins, --release-rule and
the round flags --stall-rounds, --departure-margin and --max-database-mb included): a second call with other options is refused
(one line, exit 2) unless --overwrite, which starts the folder again; the earlier run is moved to ``.DIR.replaced``
beside it and removed once the new run finishes (a folder with other files and no ``learn.json`` is refused). The exit code is the final certificate's verdict
(``certificate.exit_code``: 0 passed, 3 failed, 4 below the minimum certificate; bad input 2),
also printed and stored in ``ann.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Sequence

from homogenization.learning.settings import ActiveSettings, CertificateSettings
from homogenization.cli.options import (active_settings, add_active_arguments, add_threads_argument, certificate_settings,
                                        command_parser, equilibrium_line, EXIT_CODES_HELP)
from training.config import DEFAULT_HIDDEN, HYBRID_EPOCHS, HYBRID_PATIENCE, hidden_widths, TrainConfig
from training.train import EpochBar
from warp_hcell.core.cli import positive_int, quiet_warp, say, set_verbosity, UserError
from warp_hcell.core.files import atomic_write, check_output_path, output_lock
from warp_hcell.core.parameters import DatabaseSettings
from warp_hcell.core.provenance import file_sha256
from warp_hcell.mesostructures.builders import mesostructure_arg, MESOSTRUCTURE_HELP
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.mesostructures.mesostructure import MesostructureError


def build_parser() -> argparse.ArgumentParser:
    """Parser of ``hmodel learn`` (budget and certificate flags ``add_active_arguments``, database from ``DatabaseSettings``)."""
    db = DatabaseSettings()
    parser = command_parser("homogenization.learn", "Database, meso-ANN, certificate and active-learning rounds "
                            "of one mesostructure (docs/certificate.md).")
    parser.add_argument("--mesostructure", type=mesostructure_arg, required=True, help=MESOSTRUCTURE_HELP)
    parser.add_argument("--out", type=Path, required=True, help="folder of db.h5, ann.pt/.json, certificate.png")
    parser.add_argument("--samples", type=positive_int, default=db.samples, help="samples of the generated database")
    parser.add_argument("--hidden", type=hidden_widths, default=DEFAULT_HIDDEN,
                        help="hidden widths of the network, comma separated")
    parser.add_argument("--epochs", type=positive_int, default=None, help="maximum training epochs (training's default)")
    add_active_arguments(parser)
    parser.add_argument("--no-rollout", action="store_true", help="leave out the single-cell rollouts")
    add_threads_argument(parser, "DEM and torch CPU threads", 1)
    parser.epilog = EXIT_CODES_HELP
    return parser


ROUND_OPTIONS = ("stall_rounds", "departure_margin", "max_database_mb")
"""The round flags that ``learn.json`` records (``ActiveSettings`` fields); a record written
before they were recorded reads as their defaults (``_recorded``)."""


def _options(args: argparse.Namespace, meso, measured: CertificateSettings) -> dict:
    """What identifies a run (``learn.json``): a second call must give the same. The surrogate the
    certificate measures (``measured``: K and tolerance where it is the hybrid, the flags' or the
    cell's default) and the round flags ``ROUND_OPTIONS`` included."""
    return {"mesostructure": args.mesostructure.text, "mesostructure_sha256": description_sha256(describe(meso)),
            "samples": args.samples, "seed": args.seed, "hidden": list(args.hidden), "epochs": args.epochs,
            "orientations": args.orientations, "spatial_rule": list(measured.spatial_rule),
            "release_rule": measured.release_rule, "eps_max": args.eps_max, "rollout": not args.no_rollout,
            **{name: getattr(args, name) for name in ROUND_OPTIONS},
            **({"equilibrium_corrections": measured.equilibrium_corrections,
                "equilibrium_tolerance": measured.equilibrium_tolerance} if measured.equilibrium_corrections else {})}


def _recorded(path: Path) -> dict:
    """The options of ``learn.json`` at ``path``, the round flags it lacks (``ROUND_OPTIONS``), the 3D certificate's
    rule (--order, --spins) and --release-rule at their defaults."""
    defaults, measured = ActiveSettings(), CertificateSettings()
    return {**{name: getattr(defaults, name) for name in ROUND_OPTIONS}, "spatial_rule": list(measured.spatial_rule),
            "release_rule": measured.release_rule, **json.loads(path.read_text())}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (bad input: one line, 2, before any work; then the
    certificate's verdict, ``certificate.exit_code``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    budget = active_settings(args)
    try:
        settings = DatabaseSettings(samples=args.samples)
        meso = args.mesostructure.build()
    except (ValueError, MesostructureError) as exc:
        raise UserError(str(exc)) from None
    measured = certificate_settings(args, meso)
    if measured.equilibrium_corrections and meso.dim != 3:
        raise UserError(f"--equilibrium-corrections: spatial cells only ({args.mesostructure.text} is {meso.dim}D)")
    out: Path = args.out
    config = _train_config(args, measured)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder")
    check_output_path(out, overwrite=True)  # the nearest existing folder above --out can be written
    record, options = out / "learn.json", _options(args, meso, measured)
    replaced = out.parent / f".{out.name}.replaced"
    if not args.verbose:
        quiet_warp()
    with output_lock(out):
        if out.is_dir() and any(out.iterdir()) and not record.is_file():
            raise UserError(f"--out {out} holds files that are not a learn run; give a new or empty folder")
        if record.is_file() and (args.overwrite or _recorded(record) != options):
            if not args.overwrite:
                raise UserError(f"{out} holds a learn run with other options; rerun it with the same options or "
                                f"pass --overwrite to start again")
            if replaced.exists():  # out is an unfinished run that replaces it: the finished one stays
                shutil.rmtree(out)
            else:
                out.rename(replaced)
            say(f"the earlier run is kept in {replaced} until this one finishes")
        out.mkdir(parents=True, exist_ok=True)
        with atomic_write(record) as tmp:
            tmp.write_text(json.dumps(options, indent=1, sort_keys=True) + "\n")
        say(equilibrium_line(measured, args.equilibrium_corrections is not None)
            + (f"; training {config.epochs} epochs at most, patience {config.patience}" if measured.equilibrium_corrections
               else ""))
        code = _learn(args, out, meso, settings, budget, measured, config)
        shutil.rmtree(replaced, ignore_errors=True)  # this run finished: the one it replaces goes
        return code


def _database_complete(path: Path) -> bool:
    from warp_hcell.database import format as database  # noqa: PLC0415 (h5py: only when the command runs)

    try:
        database.check_database(path)
    except ValueError:
        return False
    return True


def _train_config(args: argparse.Namespace, measured: CertificateSettings) -> TrainConfig:
    """The training settings of the run (training's defaults but for --hidden, --threads, --seed,
    --device, --epochs and --no-rollout; a hybrid surrogate's network, ``measured`` with
    equilibrium corrections: at most ``HYBRID_EPOCHS`` epochs without --epochs, patience
    ``HYBRID_PATIENCE``)."""
    hybrid = {"epochs": HYBRID_EPOCHS, "patience": HYBRID_PATIENCE} if measured.equilibrium_corrections else {}
    return TrainConfig(hidden=tuple(args.hidden), threads=args.threads, seed=args.seed, device=args.device,
                       rollout=not args.no_rollout, **{**hybrid, **({"epochs": args.epochs} if args.epochs else {})})


def _learn(args: argparse.Namespace, out: Path, meso, settings: DatabaseSettings,
           budget: ActiveSettings, measured: CertificateSettings, config: TrainConfig) -> int:
    from homogenization.learning import active, certificate  # noqa: PLC0415 (torch and Warp: only when the command runs)
    from training.card import read_card  # noqa: PLC0415
    from training.checkpoint import metadata_path  # noqa: PLC0415
    from warp_hcell.database.generate import generate  # noqa: PLC0415
    from warp_hcell.database.shards import DiskFull  # noqa: PLC0415

    db, model, figure = out / "db.h5", out / "ann.pt", out / "certificate.png"
    bar = EpochBar()
    generated = not _database_complete(db)
    if not generated:
        say(f"database: {db} (done before)")
    else:
        try:
            generate(meso, settings, db, seed=args.seed, device=args.device, threads=args.threads,
                     discard_partial=True)
        except DiskFull as exc:
            raise UserError(f"no space left on the device writing {exc.filename}; free space and rerun the same "
                            f"command to resume") from None
        say(f"database: {db}, {settings.samples} samples")
    active.finish_promotion(model)  # a round's model moved in half before an interruption
    card = read_card(model) if metadata_path(model).is_file() and model.is_file() else None
    # the kept model of earlier rounds on this database: a round's samples (a rejected round's, or appended before an
    # interruption) change db.h5 after it; the rounds go on from their record
    of_rounds = card is not None and not generated and bool(card.active_learning)
    if card is not None and (of_rounds or card.training_data["sha256"] == file_sha256(db)):
        say(f"model: {model} (done before)")
    else:
        card = active.train_model(db, model, config, [], progress=bar, log=say)
    rounds, cert = active.learn(db, model, config, settings=budget, seed=args.seed, threads=args.threads, log=say,
                                progress=bar,
                                certify_settings=measured, card=card)
    stamp = out / "certificate.png.sha256"
    if figure.is_file() and stamp.is_file() and stamp.read_text().strip() == cert.model_sha256:
        say(f"figure: {figure} (done before)")
    else:
        certificate.plot_worst_test(model, cert, figure, threads=args.threads)
        stamp.write_text(cert.model_sha256 + "\n")
        say(f"figure: {figure}")
    say(*certificate.summary_lines(cert),
        f"{len(rounds) - 1} active round(s), {rounds[-1].samples_total} samples in {db}")
    return certificate.exit_code(cert)
