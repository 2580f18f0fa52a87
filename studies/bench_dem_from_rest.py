"""python studies/bench_dem_from_rest.py [--mesostructure CELL] [--rates 5e-6,2.5e-6,1e-6,5e-7]

Increments from rest (docs/dem_stepping.md, "Increments from rest"): one triaxial test run by the DEM
(defaults, with its velocity memory) and by the DEM started from rest in every increment
(``homogenization.learning.from_rest.FromRest``, the map the database samples) at each driving rate
``DemSettings.rest_strain_per_substep`` of ``--rates``. Prints, per rate, the largest difference of p or q
from the DEM's over the shear stage as a fraction of max(p0, the DEM's largest p), up to ``--within``
and to the end, and the wall time of the run; a run whose stress control stops is reported so, in one line.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np

from warp_hcell.core.cli import Parser, positive_float, positive_int


def _floats(text: str) -> list[float]:
    return [positive_float(part) for part in text.split(",")]


def main(argv=None) -> int:
    parser = Parser(description=__doc__.split("\n\n")[1])
    parser.add_argument("--mesostructure", default="benchmarks/cells/large_axial.toml",
                        help="3D cell: builder spec or file")
    parser.add_argument("--test", choices=("undrained", "drained"), default="drained")
    parser.add_argument("--p0", type=positive_float, default=2e5, help="isotropic pressure [Pa]")
    parser.add_argument("--eps-max", type=positive_float, default=0.15, help="axial strain of the shear stage [-]")
    parser.add_argument("--within", type=positive_float, default=0.10,
                        help="axial strain up to which the first column measures [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--order", type=positive_int, default=11, help="Lebedev order of the cell axes")
    parser.add_argument("--spins", type=positive_int, default=4, help="spins per axis")
    parser.add_argument("--rates", type=_floats, default=[5e-6, 2.5e-6, 1e-6, 5e-7],
                        help="comma-separated strains per substep of an increment from rest [-]")
    args = parser.parse_args(argv)

    from homogenization.element_test import driver, programme as programmes
    from homogenization.learning.from_rest import FromRest
    from warp_hcell.core.parameters import ContactLaw, DemSettings
    from warp_hcell.dem.cell import DemCell
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(args.mesostructure).build(None)
    programme = programmes.triaxial(args.p0, args.eps_max, args.increment, test=args.test,
                                 iso_increment=0.5 * args.increment)

    def run(model):
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            record = driver.run(model, programme, mesostructure=meso, lebedev_order=args.order,
                                n_spins=args.spins, progress=False)
        shear = record.stage != record.programme[0].label
        return record.p[shear], record.q[shear], time.perf_counter() - start

    p, q, wall = run(DemCell(ContactLaw(), 0.5, threads=1))
    scale = max(args.p0, float(p.max()))
    within = int(round(args.within / args.increment))
    print(f"{args.mesostructure}, {args.test}, p0 = {args.p0:g} Pa, to {args.eps_max:g} at {args.increment:g}, "
          f"Lebedev {args.order} x {args.spins}; the DEM: {wall:.1f} s")
    print(f"{'from rest at':>13} | {f'to {args.within:g}':>10} | {f'to {args.eps_max:g}':>10} | wall s")
    for rate in args.rates:
        settings = replace(DemSettings(), rest_strain_per_substep=rate)
        try:
            p_rest, q_rest, wall = run(FromRest(DemCell(ContactLaw(), 0.5, settings=settings, threads=1)))
        except driver.ControlError as exc:
            print(f"{rate:>13g} | stopped: {' '.join(str(exc).split())}")
            continue
        off = np.maximum(np.abs(p_rest - p), np.abs(q_rest - q)) / scale
        print(f"{rate:>13g} | {100 * off[:within].max():9.3f}% | {100 * off.max():9.3f}% | {wall:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
