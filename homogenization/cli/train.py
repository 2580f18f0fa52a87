"""hmodel train --data db.h5 --out model.pt [--no-certify] [training options]

(also ``python -m homogenization.train``.) Trains the meso-ANN (``training.train``, the same
options and output), then, unless --no-certify, measures the model against the DEM of its
mesostructure (``homogenization.certificate``, docs/certificate.md) and writes the certificate
into the model's JSON, so that the ANN backend accepts a model that passed. A model that fails
is written all the same, with its failed certificate (exit 0: a failed certificate is a
result; the backend then refuses the model unless --uncertified-ok).

Training lives in ``training/``, which never imports ``homogenization``, where the driver and
the DEM backend of the certificate are; this command joins the two. ``python -m
training.train`` alone leaves the model uncertified and says how to certify it.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from homogenization import certificate
from training import train as training_train
from warp_hcell.core.cli import command_prog, say


def build_parser() -> argparse.ArgumentParser:
    """The training parser (``training.train.build_parser``) plus --no-certify."""
    parser = training_train.build_parser()
    parser.prog = command_prog("homogenization.train")
    parser.add_argument("--no-certify", action="store_true",
                        help="leave the model uncertified (the ANN backend refuses it without --uncertified-ok)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (bad input: one line, 2, before any training)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    code = training_train.main([a for a in argv if a != "--no-certify"])
    if code or args.no_certify:
        return code
    cert = certificate.certify(args.out)
    say(*certificate.summary_lines(cert), f"certificate -> {certificate.write_certificate(args.out, cert)}")
    return 0
