"""hmodel plot RUN [RUN ...] --out fig.png|fig.pdf|fig.svg [--deviator t] [--fourth-panel W2] [--normalise] [--csl]

(also ``python -m homogenization.plotting``.) Overlays finished runs (run.h5 files or their folders) in the
2x2 biaxial figure of ``homogenization.output.figures``; whether the third panel shows p or eps_v is read from the files
(``drained`` parameter, else: a stress-controlled component after the first step).

Sign convention: compression and contraction positive; stresses in N/m (2D).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from homogenization.output import figures, io
from warp_hcell.core.cli import command_parser, run_main, say, set_verbosity, UserError, writing_to
from warp_hcell.core.files import check_output_path


def add_figure_arguments(parser: argparse.ArgumentParser) -> None:
    """The figure flags shared by ``hmodel plot`` and ``hmodel biaxial``: --deviator, --fourth-panel,
    --normalise, --csl."""
    parser.add_argument("--deviator", choices=figures.DEVIATORS, default=figures.DEVIATORS[0], help="q = s11 - s22 or t = q/2")
    parser.add_argument("--fourth-panel", choices=figures.FOURTH_PANELS, default=figures.FOURTH_PANELS[0],
                        help="fourth panel: stress ratio or second-order work W2")
    parser.add_argument("--normalise", action="store_true",
                        help="draw stresses divided by each run's p0 (q/p0, p/p0, W2/p0), so runs at different p0 "
                             "compare")
    parser.add_argument("--csl", action="store_true",
                        help="draw each run's critical-state line: " + figures.CSL_RULE.replace("%", "%%"))


def build_parser() -> argparse.ArgumentParser:
    """Parser of the replot command."""
    parser = command_parser(
        "homogenization.plotting",
        "Overlay finished runs (run.h5 files of hmodel biaxial) in the 2x2 biaxial figure. Legend labels "
        "and title come from the runs' metadata: the parts every run shares (test, backend, "
        "mesostructure, alpha0, p0, N) make the title, the parts that differ the legend.",
        device=False)
    parser.add_argument("runs", type=Path, nargs="+", metavar="RUN", help="run files (run.h5) or run folders to overlay")
    parser.add_argument("--out", type=Path, required=True, help="figure file: .png, .pdf or .svg")
    add_figure_arguments(parser)
    parser.add_argument("--title", default=None, help="figure title (None: what the runs share)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing figure")
    return parser


def warn(message: str) -> None:
    """One warning line on stderr."""
    print(f"hmodel plot: warning: {message}", file=sys.stderr)


def csl_summary(slopes: Sequence[float | None]) -> str:
    """ "critical-state lines: k of n runs" (the others were warned about: no critical state reached)."""
    return f"critical-state lines: {sum(m is not None for m in slopes)} of {len(slopes)} runs"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    figures.figure_format(args.out)
    if args.out.is_dir():
        raise UserError(f"--out {args.out} is a folder; give a file name")
    check_output_path(args.out, overwrite=args.overwrite)
    runs = [figures.Run(stored.record, stored.attrs["parameters"]) for stored in map(io.read_run, args.runs)]
    parser = build_parser()
    planar_only = [flag for flag, dest in (("--csl", "csl"), ("--normalise", "normalise"), ("--deviator", "deviator"),
                                           ("--fourth-panel", "fourth_panel"))
                   if getattr(args, dest) != parser.get_default(dest)]
    if planar_only and any(figures.triaxial_runs([run]) for run in runs):
        raise UserError(f"{', '.join(planar_only)} apply to planar (biaxial) runs; the figure of 3D runs draws their "
                        f"q, p and eps_v as hmodel triaxial does")
    if len({figures.run_drained(run) for run in runs}) > 1:
        raise UserError("the runs mix drained and constant-volume tests; plot each kind separately")
    if args.normalise:
        missing = [path for path, run in zip(args.runs, runs) if figures.reference_pressure(run) is None]
        if missing:
            raise UserError(f"--normalise: {missing[0]} stores no p0 (no p0 parameter, no stop_at_p step)")
    slopes = (figures.critical_state_lines(runs, [str(path) for path in args.runs], warn, report=say)
              if args.csl else None)
    fig = figures.overlay_figure(runs, fourth=args.fourth_panel, deviator=args.deviator, normalise=args.normalise,
                         csl=slopes, title=args.title)
    with writing_to(args.out):
        figures.save_figure(fig, args.out)
    say(f"figure -> {args.out}" + (f" ({csl_summary(slopes)})" if slopes is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
