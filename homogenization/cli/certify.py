"""hmodel certify --model M.pt [--mesostructure SPEC] [--data DB.h5] [--write] [--out FILE]
[--equilibrium-corrections K [--equilibrium-tolerance R]] [--release-rule resting|drag]

(also ``python -m homogenization.certify``.) The certificate of a meso-ANN model
(``homogenization.learning.certificate.certify``, docs/certificate.md): the command prints one line per
test, the verdict and the envelope, and exits with the verdict (``certificate.exit_code``: 0
passed, 3 failed, 4 within the target but below the minimum certificate; the certificate is
recorded in every case). ``--write`` stores it in the model's JSON under ``"certificate"`` (the
ANN backend then checks it), ``--out`` writes it to a JSON file (an existing one only with
--overwrite). ``--data DB.h5`` first (re)builds the model's out-of-distribution index from its
database (``training.ood.index_for_model``), for a model trained before the index existed.
``--equilibrium-corrections K`` certifies the hybrid (the ANN followed by up to K exact Newton
steps; ``AnnCell``): the certificate records K and the tolerance, and covers runs with those only.
Without it, the default surrogate of the model's cell (``settings.default_equilibrium``: the
hybrid for a 3D cell with fine grains, the network alone for any other), said in one line.

Bad input (missing model or JSON, a mesostructure the model does not take, --out a folder, an
existing file without --overwrite or in a folder that cannot be written, --write on a JSON that
cannot be written, --data not a database) is one line and exit 2, before any test. The parser
reads its defaults from ``homogenization.learning.settings.CertificateSettings`` (the minimum
certificate), so that --help imports neither torch nor Warp.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
from pathlib import Path
from typing import Sequence

from homogenization.cli.options import (add_certificate_equilibrium_arguments, add_spatial_rule_arguments, certificate_settings,
                                        command_parser, equilibrium_line, EXIT_CODES_HELP)
from homogenization.learning.settings import CertificateSettings
from warp_hcell.core.cli import axial_strain, positive_float, positive_int, quiet_warp, say, set_verbosity, UserError, writing_to
from warp_hcell.core.files import atomic_write, check_output_path
from warp_hcell.mesostructures.builders import mesostructure_arg

PROG = "homogenization.certify"
"""The ``python -m`` module of the command (its usage line and the ``command`` of a certificate)."""


def build_parser() -> argparse.ArgumentParser:
    """Parser of the certificate command."""
    measured = CertificateSettings()
    parser = command_parser(PROG, "Measure a meso-ANN model against the DEM of its mesostructure (docs/certificate.md).")
    parser.add_argument("--model", type=Path, required=True, help="the model (.pt, its .json beside it)")
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None,
                        help="the cell of the tests (None: the model's own mesostructure)")
    parser.add_argument("--data", type=Path, default=None,
                        help="first (re)build the model's out-of-distribution index from this learning database")
    parser.add_argument("--write", action="store_true", help="store the certificate in the model's JSON")
    parser.add_argument("--out", type=Path, default=None, help="also write the certificate to this JSON file")
    parser.add_argument("--orientations", type=positive_int, default=measured.n_orientations,
                        help="cell orientations per test (planar cells)")
    add_spatial_rule_arguments(parser, *measured.spatial_rule, " per test")
    parser.add_argument("--eps-max", type=axial_strain, default=measured.eps_max,
                        help="axial strain of each shear stage [-]")
    parser.add_argument("--no-rollout", action="store_true", help="leave out the single-cell rollouts")
    add_certificate_equilibrium_arguments(parser)
    parser.epilog = EXIT_CODES_HELP
    return parser


def check_writable(args: argparse.Namespace) -> None:
    """UserError (one line) before any work: --out an existing file without --overwrite, a folder, the model's
    .pt or .json, or in a folder that cannot be written; --write with a model JSON or folder that cannot be written;
    --data not a file."""
    if args.out is not None:
        if args.out.is_dir():
            raise UserError(f"--out {args.out} is a folder; give a JSON file name")
        model = Path(args.model).resolve()
        if args.out.resolve() in (model, model.with_suffix(".json")):
            raise UserError(f"--out {args.out} is the model's own file; give another JSON file name (--write stores "
                            f"the certificate in the model's JSON)")
        check_output_path(args.out, overwrite=args.overwrite)
    if args.write:
        from training.checkpoint import metadata_path  # noqa: PLC0415 (torch: only when the command runs)

        meta = metadata_path(args.model)
        if not meta.is_file():
            raise UserError(f"--model {args.model}: no {meta.name} beside it (the model's JSON)")
        if not (os.access(meta, os.W_OK) and os.access(meta.parent, os.W_OK)):
            raise UserError(f"--write: cannot write to {meta} (or its folder)")
    if args.data is not None and not args.data.is_file():
        raise UserError(f"--data {args.data}: no such database file")


def rebuild_index(model: Path, data: Path, metadata: dict | None = None) -> None:
    """(Re)build ``model``'s out-of-distribution index from database ``data`` and say where it went
    (``metadata``: the model's JSON already read, None: read here)."""
    from training.checkpoint import load_checkpoint  # noqa: PLC0415 (torch: only when the command runs)
    from training.dataset import load_database  # noqa: PLC0415
    from training.ood import index_for_model, index_path  # noqa: PLC0415

    net, meta = load_checkpoint(model, metadata)
    try:
        database = load_database(data)
    except (OSError, KeyError) as exc:
        raise UserError(f"--data {data}: not a learning database ({exc})") from None
    if database.mesostructure_sha256 != meta.get("mesostructure_sha256"):
        raise UserError(f"--data {data} is a database of mesostructure {database.mesostructure_sha256[:12]}, the model's "
                        f"is {str(meta.get('mesostructure_sha256'))[:12]}: give the model's own database")
    index = index_for_model(net, meta["config"], database)
    with writing_to(index_path(model)):
        say(f"out-of-distribution index: {index.points.shape[0]} states, threshold {index.threshold:.4g} -> "
            f"{index.save(index_path(model))}")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code: 0 passed, 2 bad input (one line, before any test),
    ``EXIT_FAILED`` (3) failed, ``EXIT_WEAK`` (4) within the target but below the minimum."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    if not args.model.is_file():
        raise UserError(f"--model {args.model}: no such model file")
    check_writable(args)
    certificate_settings(args)  # its one-line errors before torch is imported
    from homogenization.learning import certificate  # noqa: PLC0415 (torch and Warp: only when the command runs)
    from homogenization.element_test import driver
    from training.card import read_card  # noqa: PLC0415
    from training.checkpoint import metadata_path  # noqa: PLC0415
    from warp_hcell.mesostructures.files import from_description  # noqa: PLC0415

    card = read_card(args.model)  # CheckpointError (one line) for a missing or unreadable JSON
    measured = certificate_settings(args, from_description(card.mesostructure))
    say(equilibrium_line(measured, args.equilibrium_corrections is not None))
    if not args.verbose:
        quiet_warp()
    meso = args.mesostructure.build(None) if args.mesostructure is not None else None
    if args.data is not None:
        rebuild_index(args.model, args.data, card.to_dict())
    try:
        cert = certificate.certify(args.model, mesostructure=meso, card=card, **measured.keywords())
    except driver.ControlError as exc:
        raise UserError(f"a test did not converge: {exc}") from None
    if argv is not None:
        cert = dataclasses.replace(cert, command=shlex.join(["python", "-m", PROG, *argv]))
    say(*certificate.summary_lines(cert))
    if args.out is not None:
        with writing_to(args.out), atomic_write(args.out) as tmp:
            tmp.write_text(json.dumps(cert.to_dict(), indent=2, sort_keys=True) + "\n")
    if args.write:
        with writing_to(metadata_path(args.model)):
            say(f"certificate -> {certificate.write_certificate(args.model, cert, card)}")
    return certificate.exit_code(cert)
