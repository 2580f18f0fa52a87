"""python -m warp_hcell.generate [--mesostructure FILE_OR_SPEC] --samples 300000 --seed 0 --out runs/db.h5

The command of the learning database (``warp_hcell.database.generate``): ``--mesostructure`` takes a
file or a builder spec (``warp_hcell.mesostructures.builders``); without it the cell is
``hcell.h_cell`` and the exploration starts from H-cells of several opening angles
(``hcell.StartCells``). It draws the probes' progress bar and prints where it wrote.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Iterable, Sequence

from warp_hcell.core.cli import (
    UserError,
    ProgressBar,
    command_parser,
    finite_float,
    positive_float,
    positive_int,
    progress_bar,
    run_main,
    say,
    set_verbosity,
    task_setup,
)
from warp_hcell.core.execution import make_execution, SchedulerUnreachable
from warp_hcell.core.files import check_output_path
from warp_hcell.core.parameters import CellDefaults, DatabaseSettings
from warp_hcell.database.exploration import UnreachableLevel
from warp_hcell.database.generate import generate
from warp_hcell.database.shards import DiskFull
from warp_hcell.mesostructures.builders import mesostructure_arg, MESOSTRUCTURE_HELP
from warp_hcell.mesostructures.hcell import StartCells, h_cell
from warp_hcell.mesostructures.mesostructure import MesostructureError


def _walk_bar(steps: Iterable[int], label: str) -> Iterable[int]:
    """An exploration walk's increments in a progress bar named ``label``, erased at its end on a
    terminal (module level: Dask pickles it)."""
    return progress_bar(steps, desc=label, unit="increment", leave=False)


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m warp_hcell.generate`` argument parser (defaults from ``DatabaseSettings``)."""
    defaults = DatabaseSettings()
    parser = command_parser(
        "warp_hcell.generate",
        "Generate the generic meso-ANN learning database of a mesostructure with the DEM "
        "(docs/database_format.md): exploration paths, then seeded strain probes and perturbed states of "
        "the sampled states.")
    parser.add_argument("--out", type=Path, required=True, help="database file (HDF5) to write")
    parser.add_argument("--mesostructure", type=mesostructure_arg, default=None,
                        help=MESOSTRUCTURE_HELP + " (a spec without alpha0 is built at "
                             f"{CellDefaults.alpha0_deg:g} deg); unset: the H-cell, explored from "
                             "H-cells of several opening angles")
    parser.add_argument("--samples", type=positive_int, default=defaults.samples, help="number of samples")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="worker processes of a local Dask cluster (1: in this process; the result does not "
                             "depend on it)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run the tasks on this Dask scheduler (e.g. tcp://host:8786) instead of locally")
    parser.add_argument("--threads", type=positive_int, default=2,
                        help="DEM CPU threads per process (the result does not depend on it)")
    parser.add_argument("--chunk-size", type=positive_int, default=defaults.chunk_size,
                        help="probes per batch (unit of resume and of parallel work)")
    parser.add_argument("--max-chunks", type=positive_int, default=None,
                        help="compute at most this many chunks, then stop (rerun to resume)")
    parser.add_argument("--sample-spacing", type=positive_float, default=defaults.sample_spacing,
                        help="path length between sampled states along the exploration paths [-]")
    parser.add_argument("--n-directions", type=positive_int, default=defaults.n_directions,
                        help="proportional-leg directions in the local strain space ((eps_n, eps_t) plane; "
                             "a spherical Fibonacci set for a 3D cell)")
    parser.add_argument("--n-alpha0", type=positive_int, default=StartCells.n_alpha0,
                        help="default H-cell only: start cells at opening angles evenly spaced in [30, 89] deg "
                             "(plus 35, 40, 55)")
    parser.add_argument("--perturbed-fraction", type=float, default=defaults.perturbed_fraction,
                        help="fraction of probes starting from a perturbed (unbalanced) state")
    parser.add_argument("--reversal-legs", type=int, default=defaults.reversal_legs,
                        help="turning branches per proportional leg (unloading / reloading states; 0 = none)")
    parser.add_argument("--precompression", type=finite_float, nargs="+", default=list(defaults.precompression),
                        metavar="EPS", help="isotropic strains [-] from which the proportional legs start")
    parser.add_argument("--clean", action="store_true",
                        help="apply the cleaning step (warp_hcell.clean: unconverged, non-finite) to `valid`")
    return parser


def _run(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    try:
        settings = DatabaseSettings(samples=args.samples, chunk_size=args.chunk_size,
                                    sample_spacing=args.sample_spacing, n_directions=args.n_directions,
                                    perturbed_fraction=args.perturbed_fraction, reversal_legs=args.reversal_legs,
                                    precompression=tuple(args.precompression))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_output_path(args.out, overwrite=args.overwrite)
    if args.out.is_dir():
        raise UserError(f"{args.out} is a folder; --out must be a file")
    if args.mesostructure is not None and args.n_alpha0 != StartCells.n_alpha0:
        raise UserError("--n-alpha0 sets the plain H-cell's start cells; a --mesostructure starts from itself alone")
    if args.mesostructure is None:
        meso = h_cell(CellDefaults.alpha0_deg, CellDefaults.radius)
        starts = StartCells(n_alpha0=args.n_alpha0).build(CellDefaults.radius)
    else:
        try:
            meso = args.mesostructure.build()
        except MesostructureError as exc:
            raise UserError(str(exc)) from None
        starts = [meso]
    start = time.perf_counter()
    bar = ProgressBar(desc="probes", unit="sample", smoothing=0.1)
    try:
        with make_execution(args.workers, args.scheduler, setup=task_setup(args)) as execution:
            written = generate(meso, settings, args.out, seed=args.seed, starts=starts, device=args.device,
                               threads=args.threads, execution=execution, clean=args.clean,
                               max_chunks=args.max_chunks, discard_partial=args.overwrite, progress=bar,
                               explore_progress=_walk_bar)
    except (SchedulerUnreachable, UnreachableLevel) as exc:
        raise UserError(str(exc)) from None
    except DiskFull as exc:
        raise UserError(f"no space left on the device writing {exc.filename}; free space and rerun the same "
                        f"command to resume") from None
    finally:
        bar.close()
    elapsed = time.perf_counter() - start
    if written is None:
        say(f"stopped after --max-chunks {args.max_chunks} ({elapsed:.1f} s); rerun the same command to resume")
    else:
        say(f"{written}: {settings.samples} samples in {elapsed:.1f} s ({settings.samples / elapsed:.0f} samples/s)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point; bad input is one line on stderr and exit code 2."""
    return run_main(_run, argv)


if __name__ == "__main__":
    sys.exit(main())
