"""python benchmarks/bench_dem_target.py [--cells 1000] [--increment 1e-5] [--repeat 5]

Speed cost of the DEM's pinned compile target (``warp_hcell.dem.warp_options``: generic x86-64, no
FMA contraction) against Warp's default ``-march=native`` (the host's instruction set), side by
side: ``benchmarks/bench_dem3d.py`` (one thread, 2D six-disk and 3D ten-sphere H-cells, cell-substeps
per CPU-second) runs in one subprocess per target, alternating, ``--rounds`` times, best kept.
Each target compiles its own kernels (Warp's cache keys them by flags). Prints one line per cell
kind: both rates and native/pinned.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from warp_hcell.core.cli import Parser, positive_int

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"pinned": None, "native": "-march=native"}
"""Target name -> ``cpu_compiler_flags`` put into ``MODULE_OPTIONS`` before the DEM is imported (None: as shipped)."""
RUNNER = """import runpy, sys
import warp_hcell.dem.warp_options as options
flags = sys.argv[1]
if flags != "-":
    options.MODULE_OPTIONS["cpu_compiler_flags"] = flags
sys.argv = ["bench_dem3d.py", *sys.argv[2:]]
runpy.run_path({bench!r}, run_name="__main__")
"""


def run_target(flags: str | None, argv: list[str]) -> dict[str, float]:
    """Cell kind -> cell-substeps per CPU-second of one ``bench_dem3d`` run compiled with ``flags``."""
    code = RUNNER.format(bench=str(ROOT / "benchmarks" / "bench_dem3d.py"))
    out = subprocess.run([sys.executable, "-c", code, flags or "-", *argv], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    return {row["cell"]: row["cell_substeps_per_cpu_s"] for row in rows}


def main(argv: list[str] | None = None) -> int:
    parser = Parser(description=__doc__.splitlines()[2])
    parser.add_argument("--cells", type=positive_int, default=1000, help="cells per batch")
    parser.add_argument("--increment", default="1e-5", help="magnitude of the timed increment [-]")
    parser.add_argument("--repeat", type=positive_int, default=5, help="timed repetitions per run (best kept)")
    parser.add_argument("--rounds", type=positive_int, default=2, help="runs per target, alternating (best kept)")
    args = parser.parse_args(argv)
    forwarded = ["--cells", str(args.cells), "--increment", args.increment, "--repeat", str(args.repeat)]
    best: dict[str, dict[str, float]] = {name: {} for name in TARGETS}
    for _ in range(args.rounds):
        for name, flags in TARGETS.items():
            for kind, rate in run_target(flags, forwarded).items():
                best[name][kind] = max(best[name].get(kind, 0.0), rate)
    for kind in best["pinned"]:
        pinned, native = best["pinned"][kind], best["native"][kind]
        print(f"{kind}: pinned {pinned:.3e}, native {native:.3e} cell-substeps per CPU-second, "
              f"native/pinned = {native / pinned:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
