"""hmodel train --data db.h5 --out model.pt [--no-enrich | --no-certify] [budget flags] [training options]

(also ``python -m homogenization.train``.) Trains the meso-ANN (``training.train``, the same
options and output), then measures the model against the DEM of its mesostructure
(``homogenization.learning.certificate``, docs/certificate.md) and writes the certificate into the
model's JSON, so that the ANN backend accepts a model that passed. When the certificate fails,
the active-learning rounds of ``homogenization.learning.active`` follow (the budget flags and defaults
of ``hmodel learn``, ``homogenization.cli.options.add_active_arguments``): the DEM states of the
failing tests are probed, their samples appended to the database,
the model retrained and certified again, one line per round (with the database's size); they
stop when the certificate passes, the budget or the database's size budget is spent, or rounds
make no progress (one line: which test, which rounds, what they tried). The samples go into --data itself, or, where that file
or its folder is not writable or with --enrich-copy, into a copy of it beside the model
(``MODEL_db.h5``, ``enriched_path``); the output says which.

Resumable: a second call with the same options on a model whose JSON records active-learning
rounds (an interrupted or finished run of this command) continues that run instead of training
again (``active.learn``: the database's appends are atomic and list the rounds, so no round is
added twice); without such a record an existing model is refused unless --overwrite.

--no-enrich (or --rounds 0) certifies only; --no-certify leaves the model uncertified. A model
that fails is written all the same, with its failed certificate; the exit code says the verdict
(``certificate.exit_code``: 0 passed, 3 failed, 4 below the minimum certificate; 2 bad input),
and the backend refuses a model that did not pass unless --uncertified-ok.

Training lives in ``training/``, which never imports ``homogenization``, where the driver and
the DEM backend of the certificate are; this command joins the two. ``python -m
training.train`` alone leaves the model uncertified and says how to certify it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path
from typing import Sequence

from homogenization.cli.options import (active_settings, add_active_arguments, certificate_settings, equilibrium_line,
                                        EXIT_CODES_HELP)
from training import config as training_config
from training import train as training_command
from warp_hcell.core.cli import UserError, command_prog, quiet_warp, say, set_verbosity
from warp_hcell.core.files import atomic_write, output_lock, sigterm_as_interrupt
from warp_hcell.core.provenance import file_sha256

ENRICHED_SUFFIX = "_db.h5"
"""Name ending of the enriched copy of the database beside the model (``enriched_path``)."""
RESUME_MAY_CHANGE = ("threads",)
"""Training options a continued run may change (the rounds after it run with the new value)."""
ROUND_SET = ("hidden", "init_from", "seed", "round_share")
"""Training options that the active-learning rounds set themselves (wider network, warm start, the
seed of a round that restarts after a rejected one) or that act on the rounds' samples only (their share)."""


def build_parser() -> argparse.ArgumentParser:
    """The training parser (``training.train.build_parser``) plus --no-certify, --no-enrich,
    --enrich-copy and the active-learning flags (``add_active_arguments``)."""
    parser = training_command.build_parser()
    parser.prog = command_prog("homogenization.train")
    parser.add_argument("--no-certify", action="store_true",
                        help="leave the model uncertified (the ANN backend refuses it without --uncertified-ok)")
    parser.add_argument("--no-enrich", action="store_true",
                        help="certify only, no active-learning rounds when the certificate fails (as --rounds 0)")
    parser.add_argument("--enrich-copy", action="store_true",
                        help=f"add the rounds' samples to a copy of --data beside the model (MODEL{ENRICHED_SUFFIX}), "
                             "not to --data (the default where --data and its folder are writable)")
    add_active_arguments(parser)
    parser.epilog = EXIT_CODES_HELP + "; with --no-certify: 0 once trained"
    return parser


def enriched_path(args: argparse.Namespace) -> Path:
    """The database the rounds append to: --data, or ``MODEL_db.h5`` beside the model where
    --data or its folder is not writable (the append rewrites the file atomically beside
    itself) or --enrich-copy is given."""
    data: Path = args.data
    writable = os.access(data, os.W_OK) and os.access(data.parent, os.W_OK)
    return data if writable and not args.enrich_copy else args.out.with_name(args.out.stem + ENRICHED_SUFFIX)


def _continues(args: argparse.Namespace, database: Path):
    """The card (``training.card.ModelCard``) of ``args.out`` where it is the model of an earlier run
    of this command with these options: its JSON records active-learning rounds (none yet, too),
    training data --data or ``database``, and the training configuration of ``args``, but for what
    the rounds set (``ROUND_SET``: the hidden widths and training seed are those of its round 0) and --threads; None where
    it is no such model. UserError (one line) naming the options of an earlier run of this command that differ."""
    from training.card import read_card  # noqa: PLC0415 (torch: only when the command runs)
    from training.checkpoint import metadata_path  # noqa: PLC0415

    if args.overwrite or not (args.out.is_file() and metadata_path(args.out).is_file()):
        return None
    card = read_card(args.out)
    trained_on = Path(card.training_data["path"]).resolve()
    rounds = card.active_learning
    if rounds is None or trained_on not in (args.data.resolve(), database.resolve()):
        return None
    first_hidden = rounds[0]["hidden"] if rounds and "hidden" in rounds[0] else card.config["hidden"]
    ours = training_config.config_record(training_command.config_of(args))
    first_seed = rounds[0].get("train_seed") if rounds else None
    first_seed = card.config.get("seed") if first_seed is None else first_seed
    first = {"hidden": first_hidden, "seed": first_seed}  # round 0's: the rounds change them
    differ = ([k for k, v in first.items() if v != ours[k]]
              + [k for k, v in ours.items() if k not in (*ROUND_SET, *RESUME_MAY_CHANGE) and card.config.get(k) != v])
    if differ:
        raise UserError(f"{args.out} is the model of a run with other training options ({', '.join(differ)}): rerun "
                        f"that command to continue it, or pass --overwrite to train again")
    return card


def _uncertified(args: argparse.Namespace, config):
    """The card of ``args.out`` where it is a model this command trained with these options on --data and has not yet
    certified (an interruption during its certificate); None otherwise (--overwrite: None)."""
    from training.card import read_card  # noqa: PLC0415 (torch: only when the command runs)
    from training.checkpoint import metadata_path  # noqa: PLC0415

    if args.overwrite or not (args.out.is_file() and metadata_path(args.out).is_file()):
        return None
    card = read_card(args.out)
    same = (card.certificate is None and card.config == training_config.config_record(config)
            and card.training_data.get("sha256") == file_sha256(args.data))
    return card if same else None


def _database_mesostructure(path: Path):
    """The ``Mesostructure`` of the cells of database ``path`` (UserError, one line, before any
    training, where ``path`` is not a database of this format)."""
    from warp_hcell.database.format import check_database  # noqa: PLC0415 (h5py: only when the command runs)
    from warp_hcell.mesostructures.files import from_description  # noqa: PLC0415

    try:
        check_database(path)
        import h5py  # noqa: PLC0415

        with h5py.File(path, "r") as f:
            return from_description(f.attrs["mesostructure"])
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"--data {path}: {exc}") from None


def _require_spatial_database(path: Path) -> None:
    """One line (UserError) before any training unless ``path`` is a database of 3D cells: the
    equilibrium corrections exist for spatial cells only."""
    from warp_hcell.database.format import strain_dimension  # noqa: PLC0415 (h5py: only when the command runs)

    try:
        dim = strain_dimension(path)
    except (OSError, ValueError) as exc:
        raise UserError(str(exc)) from None
    if dim != 3:
        raise UserError(f"--equilibrium-corrections: spatial cells only ({path} holds {dim}D cells)")


def surrogate_of(args: argparse.Namespace):
    """The certificate settings of ``args`` (``certificate_settings``; without
    --equilibrium-corrections the default surrogate of the database's cell), with --epochs and
    --patience not given set to those of a hybrid's network where it is one
    (``training.train.for_hybrid``); UserError (one line) for corrections asked on a planar
    database, before any training."""
    certificate_settings(args)  # its one-line errors first
    if args.equilibrium_corrections:
        _require_spatial_database(args.data)
    explicit = args.no_certify or args.equilibrium_corrections is not None
    measured = certificate_settings(args, None if explicit else _database_mesostructure(args.data))
    if measured.equilibrium_corrections:
        training_command.for_hybrid(args)
    return measured


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (bad input: one line, 2, before any training; then the
    certificate's verdict, ``certificate.exit_code``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    budget, measured = active_settings(args), surrogate_of(args)
    from homogenization.learning import active, certificate  # noqa: PLC0415 (torch and Warp: only when the command runs)
    from training import fitting  # noqa: PLC0415
    from training.card import read_card  # noqa: PLC0415
    from training.checkpoint import metadata_path  # noqa: PLC0415

    enrich = not (args.no_certify or args.no_enrich or budget.rounds == 0)
    config = training_command.config_of(args)
    database = enriched_path(args) if enrich else args.data
    if enrich:
        active.finish_promotion(args.out)  # a round's model moved in half before an interruption
    card = _continues(args, database) if enrich else None
    resumed = card is not None
    if not args.verbose:
        quiet_warp()  # the training's rollout and the certificate run the DEM on the cpu
    bar = training_command.EpochBar()
    if not args.no_certify:
        say(equilibrium_line(measured, args.equilibrium_corrections is not None)
            + (f"; training {config.epochs} epochs at most, patience {config.patience}" if measured.equilibrium_corrections
               else ""))
    uncertified = None if enrich or args.no_certify else _uncertified(args, config)
    if resumed:
        say(f"{args.out}: an earlier run of these options, continued")
    else:
        if database != args.data and database.exists() and not args.overwrite:
            raise UserError(f"{database} exists; pass --overwrite to replace it")
        if uncertified is not None:
            say(f"{args.out}: trained before with these options, not yet certified")
        else:
            fitting.train_and_save(args.data, args.out, config, overwrite=args.overwrite, progress=bar, log=say)
        if args.no_certify:
            return 0
        card = read_card(args.out)
        if not enrich:
            with sigterm_as_interrupt():  # a kill is the one-line interruption; the same command then certifies
                cert = certificate.certify(args.out, card=card, **measured.keywords())
            say(*certificate.summary_lines(cert),
                f"certificate -> {certificate.write_certificate(args.out, cert, card)}")
            return certificate.exit_code(cert)
        card = active.write_rounds(args.out, card, [])
    if database != args.data and not (resumed and database.is_file()):
        with atomic_write(database) as tmp:
            shutil.copyfile(args.data, tmp)
    say(f"active learning adds its samples to {database}" + ("" if database == args.data else
        f" (a copy of {args.data}: {'--enrich-copy' if args.enrich_copy else 'that file or its folder is not writable'})"))
    with output_lock(database):
        rounds, cert = active.learn(database, args.out, config, settings=budget, certify_settings=measured, progress=bar,
                                    seed=args.seed, threads=args.threads, card=card, log=say)
    say(*certificate.summary_lines(cert), f"{len(rounds) - 1} active round(s), {rounds[-1].samples_total} samples "
        f"in {database}; certificate -> {metadata_path(args.out)}")
    return certificate.exit_code(cert)
