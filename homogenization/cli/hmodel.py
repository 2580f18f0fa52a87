"""hmodel COMMAND [options]: the one entry point of the package (console script ``hmodel``).

Each subcommand is the ``main(argv)`` of one module, imported only when it is called (so
``hmodel --version`` and ``hmodel plot`` never import Warp or torch), and run under the
name ``hmodel COMMAND`` (``warp_hcell.core.cli.invoked_as``: its help, usage and error lines say
so). ``hmodel COMMAND --help`` shows that command's options; ``python -m MODULE`` runs the
same code. Adding a subcommand is one line in ``COMMANDS``.

Exit codes: 0 success, 2 bad input (one line on stderr), 130 interrupted; ``certify``, ``train``
and ``learn`` exit 3 when the certificate failed and 4 when it is below the minimum certificate
(``homogenization.learning.certificate.exit_code``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from warp_hcell.core.cli import EXIT_INTERRUPTED, EXIT_USAGE, invoked_as, Parser, run_main
from warp_hcell.core.provenance import DISTRIBUTION, package_version

COMMANDS: dict[str, tuple[str, str]] = {
    "biaxial": ("homogenization.biaxial", "isotropic compression to p0, then biaxial shear or a --programme file"),
    "cell": ("homogenization.cell", "element test of one cell along a local strain path"),
    "plot": ("homogenization.plotting", "overlay finished runs (run.h5) in the 2x2 biaxial figure"),
    "generate": ("warp_hcell.generate", "DEM learning database of strain probes"),
    "clean": ("warp_hcell.clean", "mark pathological samples of a learning database"),
    "train": ("homogenization.train", "train the meso-ANN on a learning database, then certify it (--no-certify)"),
    "certify": ("homogenization.certify", "measure a meso-ANN model against the DEM: its certificate"),
    "learn": ("homogenization.learn", "database, meso-ANN, certificate and active-learning rounds of a mesostructure"),
    "sweep": ("homogenization.sweep", "biaxial tests over lists of mesostructures, alpha0, p0 and backends"),
    "bvp": ("homogenization.bvp", "plane-strain biaxial specimen (finite elements) of the homogenised material"),
    "triaxial": ("homogenization.triaxial", "isotropic compression to p0, then a 3D triaxial test or a --programme file"),
    "calibrate": ("homogenization.calibrate", "Bayesian calibration of the micro-parameters on measured curves"),
}
"""Subcommand -> (its ``python -m`` module, whose ``main(argv)`` runs it, one-line summary)."""


def build_parser() -> argparse.ArgumentParser:
    """Top-level parser: --version, the subcommand and everything after it."""
    width = max(map(len, COMMANDS))
    listing = "\n".join(f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items())
    parser = Parser(
        prog="hmodel",
        description="H-model homogenisation of granular materials (analytical, Warp meso-DEM and meso-ANN cells).",
        epilog=f"commands:\n{listing}\n\n'hmodel COMMAND --help' shows the options of COMMAND.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version(DISTRIBUTION)}")
    parser.add_argument("command", choices=tuple(COMMANDS), metavar="COMMAND", help="one of: " + ", ".join(COMMANDS))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="options of COMMAND")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``hmodel`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        if not argv:
            parser.error(f"give a COMMAND, one of: {', '.join(COMMANDS)}")
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, unknown command
        return exit_code(exc)
    try:
        module = importlib.import_module(COMMANDS[args.command][0])
    except KeyboardInterrupt:  # Ctrl-C while the command's modules load
        print(f"hmodel {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    try:
        with invoked_as(f"hmodel {args.command}"):
            return run_main(module.main, args.args)
    except SystemExit as exc:  # argparse of the subcommand: --help (0) or bad option (2)
        return exit_code(exc)


def exit_code(exc: SystemExit) -> int:
    """Exit status of a SystemExit: None is success, a message (already printed) is 2."""
    if exc.code is None:
        return 0
    return exc.code if isinstance(exc.code, int) else EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
