"""python studies/finegrain_large_axial_snap.py --model M.pt [M2.pt ...] [--tests NAME ...] [--variants V ...] [--cost | --certificate] [--json OUT]: why the hybrid of benchmarks/cells/large_axial.toml misses its certificate.

For each certificate test named (default: the three compression tests the models of ``large_axial.toml`` fail;
the certificate's loading and cells, Lebedev order 11 x 4 spins, ``homogenization.learning.certificate``), one
process runs the DEM, then for each model (a) the hybrid as the certificate measures it (K = 20 Newton corrections
at force ratio 1e-4, ``RELEASE_RULE``) and (b) a study-only variant, not a package option: the same hybrid with
every cell-increment that ends with a released grain (``DemEscalation.released_dofs``, those pushed from rest
included) replaced by the DEM's increment from rest (``DemEscalation.advance``), and (c) the hybrid without the
released-grain rule (``AnnCell(dem_escalation=False)``: the network's guess starts every grain's corrections; a
package option that ``hmodel certify`` does not certify for fine-grain cells), and (d) the hybrid under
``RELEASE_RULE_DRAG`` (a grain pushed from rest relaxed as the DEM does from rest; ``hmodel certify --release-rule
drag``); ``--variants`` picks among them (default: all). Prints per run: the certificate's
figure (largest abs(dp) or abs(dq) over the shear stage / max(p0, largest DEM p)), the first increment above 2 %,
the largest one-increment drop of q (the snap of a fine grain leaving its wedge) and where, the free fine grain's
x_n [m] in the cell of the DEM's largest drop at 70, 80, 90 and 100 % of the shear stage, cell-increments handed to
the DEM, the cell-increments (d) relaxed (their substeps, those at the cap) and the wall time (the machine's load
printed; times are indicative only).

``--cost``: instead, the product benchmark's runs (``benchmarks/bench_finegrain_hybrid.py``: 7792 cells, triaxial
compression at 2e5 Pa to 5 % at 1e-4, undrained and drained) of the DEM, (a) and (b) of the first model, one
process, interleaved, with each run's wall and CPU time, its largest difference from the DEM over the scale and
the cell-increments handed to the DEM.

``--certificate``: instead, the certificate (``homogenization.learning.certificate.certify``, the hybrid's default
K and R, no rollouts) of each model under variant (b), printed, never written: not a certificate of a package
surrogate.
"""

from __future__ import annotations

import json
import os
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FAILING = ("undrained compression p0=200000", "drained compression p0=200000", "drained compression p0=1e+06")
TARGET = 0.02
VARIANTS = ("certified hybrid", "released cells to the DEM (study only)", "no released-grain rule",
            "drag rule (RELEASE_RULE_DRAG)")


def released_to_dem(cell) -> None:
    """Make the hybrid ``cell`` hand every cell-increment that ends with a released grain to the DEM's increment
    from rest (counted in ``n_escalated``); study-only."""
    from homogenization.ann.cell import _with_cells

    def escalated(self, state, d_eps_local, new, response, resting=None):
        cells = self.escalation.released_dofs(new.cell_size, state.free_position, new.free_position).any(axis=1)
        response.diagnostics["n_escalated"] = float(np.count_nonzero(cells))
        if not cells.any():
            return new, response
        index = np.flatnonzero(cells)
        out = self.escalation.advance(state.cell_size[index], state.free_position[index], state.shear_force[index],
                                      np.asarray(d_eps_local, dtype=np.float64)[index])
        return _with_cells(new, response, index, out)

    cell._escalated = types.MethodType(escalated, cell)


def summary(record, dem, p0: float, cell: int, fine: str) -> dict:
    """The figures of one run against the DEM's ``dem`` (module docstring); ``cell``: the cell whose fine grain's
    x_n (observable ``fine``) is reported."""
    shear, ref = record.stage != record.stage[0], dem.stage != dem.stage[0]
    scale = max(p0, float(dem.p.max()))
    off = np.maximum(np.abs(record.p[shear] - dem.p[ref]), np.abs(record.q[shear] - dem.q[ref])) / scale
    drop = -np.diff(record.q[shear]) / scale
    above = np.flatnonzero(off > TARGET)
    n = int(shear.sum())
    at = [int(round(f * n)) for f in (0.7, 0.8, 0.9, 1.0)]
    snaps = record.snapshot_increment - int((~shear).sum())
    x = {k: float(record.snapshots[fine][int(np.argmin(np.abs(snaps - k))), cell]) for k in at}
    return {"figure": float(off.max()), "worst_increment": int(off.argmax()) + 1,
            "first_above_target": None if above.size == 0 else int(above[0]) + 1,
            "largest_q_drop": float(drop.max()), "largest_q_drop_increment": int(drop.argmax()) + 2,
            "fine_x_n": x, "to_dem": float(np.nansum(record.diagnostics.get("n_escalated_all_calls", [0.0]))),
            "relaxed": float(np.nansum(record.diagnostics.get("n_relaxed_all_calls", [0.0]))),
            "relaxed_substeps": float(np.nansum(record.diagnostics.get("n_relaxed_substeps_all_calls", [0.0]))),
            "relaxed_unconverged": float(np.nansum(record.diagnostics.get("n_relaxed_unconverged_all_calls", [0.0])))}


def variant_certificates(paths: list[str]) -> int:
    """``--certificate`` (module docstring): each model's certificate under variant (b), printed."""
    from homogenization.ann import cell as ann_cell
    from homogenization.learning import certificate

    plain_init = ann_cell.AnnCell.__init__

    def init(self, *args, **kwargs):
        plain_init(self, *args, **kwargs)
        if self.escalation is not None:
            released_to_dem(self)

    ann_cell.AnnCell.__init__ = init
    try:
        for path in paths:
            cert = certificate.certify(Path(path), equilibrium_corrections=20, equilibrium_tolerance=1e-4, rollout=False)
            print(f"{path}, released cells to the DEM (study only; not written):", *certificate.summary_lines(cert),
                  sep="\n", flush=True)
    finally:
        ann_cell.AnnCell.__init__ = plain_init
    return 0


def cost(path: str, *, card, meso, dem) -> list[dict]:
    """``--cost`` (module docstring): the rows of the DEM and of both hybrids of model ``path`` (its ``card``)."""
    import argparse

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_finegrain_hybrid as bench
    from homogenization.ann.escalation import RELEASE_RULE
    from homogenization.backends import make_cell_model

    def hybrid(variant):
        model = make_cell_model("ann", contact_law=card.law, model=Path(path), threads=1, card=card,
                                equilibrium_corrections=20, equilibrium_tolerance=1e-4, release_rule=RELEASE_RULE)
        if variant.startswith("released"):
            released_to_dem(model)
        return model

    models = {"dem": dem, **{v: hybrid(v) for v in ("certified hybrid", "released cells to the DEM (study only)")}}
    args = argparse.Namespace(p0=2e5, increment=1e-4, order=53, spins=16)
    small = argparse.Namespace(p0=2e5, increment=1e-4, order=3, spins=1)
    rows = []
    for test in ("undrained", "drained"):
        for model in models.values():
            bench.run(model, meso, small, 1e-3, test)  # compiles the kernels
        records, seconds = {}, {}
        for name, model in models.items():
            cpu = time.process_time()
            records[name], wall = bench.run(model, meso, args, 0.05, test)
            seconds[name] = (wall, time.process_time() - cpu)
            worst, scale = bench.difference(records[name], records["dem"], args.p0)
            to_dem = bench.total(records[name], "n_escalated_all_calls") if name != "dem" else 0.0
            print(f"{test} {name}: {wall:.1f} s, CPU {seconds[name][1]:.1f} s = {seconds[name][1] / seconds['dem'][1]:.3f}x "
                  f"the DEM's; max |diff| / scale {worst / scale:.2e}; cell-increments to the DEM {to_dem:.0f} of "
                  f"{records[name].n_increments * records[name].weights.size} (load {os.getloadavg()[0]:.2f})", flush=True)
            rows.append({"test": test, "run": name, "model": path, "seconds": wall, "cpu_seconds": seconds[name][1],
                         "cpu_ratio": seconds[name][1] / seconds["dem"][1], "difference": worst / scale,
                         "to_dem": to_dem})
    return rows


def main(argv=None) -> int:
    from warp_hcell.core.cli import Parser

    parser = Parser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", nargs="+", required=True, help="meso-ANN models (.pt) of large_axial.toml")
    parser.add_argument("--tests", nargs="+", default=list(FAILING), help="certificate test names")
    parser.add_argument("--cost", action="store_true", help="the product benchmark's runs of the first model instead")
    parser.add_argument("--certificate", action="store_true", help="variant (b)'s certificates instead (not written)")
    parser.add_argument("--json", default=None, help="write one JSON line per run here")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                        help="the hybrids run per model (default: all)")
    args = parser.parse_args(argv)
    for path in args.model:
        if not Path(path).is_file():
            parser.error(f"no model {path}")

    from homogenization.ann.escalation import RELEASE_RULE, RELEASE_RULE_DRAG
    from homogenization.backends import make_cell_model
    from homogenization.element_test import driver
    from homogenization.learning import certificate as cert
    from training.card import read_card
    from warp_hcell.core.parameters import DemSettings
    from warp_hcell.mesostructures.files import from_description

    cards = [read_card(Path(p)) for p in args.model]
    meso = from_description(cards[0].mesostructure)
    tests = {i["name"]: (i, prog) for i, prog in cert.tests_of(cert.PRESSURES, cert.EPS_MAX, cert.INCREMENT, 0, 3)}
    unknown = [t for t in args.tests if t not in tests]
    if unknown:
        parser.error(f"--tests: unknown {unknown}; the certificate's: {sorted(tests)}")
    fine = f"x_n{meso.radius.size}"
    law = cards[0].law
    dem = make_cell_model("dem", contact_law=law, radius=float(meso.radius.mean()),
                          settings=DemSettings(contact_tolerance=float(cards[0].contact_tolerance)), threads=1)
    print(f"{meso.name}; models {args.model}; load average {os.getloadavg()}", flush=True)
    if args.certificate:
        return variant_certificates(args.model)
    lines = cost(args.model[0], card=cards[0], meso=meso, dem=dem) if args.cost else []
    for name in ([] if args.cost else args.tests):
        info, programme = tests[name]

        def run(model):
            start = time.perf_counter()
            record = driver.run(model, programme, mesostructure=meso, progress=False, snapshot_interval=10,
                                lebedev_order=cert.SPATIAL_RULE[0], n_spins=cert.SPATIAL_RULE[1], staggered_spins=True)
            return record, time.perf_counter() - start

        reference, wall = run(dem)
        shear = reference.stage != reference.stage[0]
        cell = int(np.argmin(reference.snapshots["S_nn"][-1] - reference.snapshots["S_nn"][-2]))
        base = summary(reference, reference, info["p0"], cell, fine)
        print(f"{name}: DEM {wall:.1f} s (load {os.getloadavg()[0]:.2f}); its largest one-increment q drop "
              f"{100 * base['largest_q_drop']:.2f} % of the scale at shear increment {base['largest_q_drop_increment']} "
              f"of {int(shear.sum())}; fine grain x_n of cell {cell}: "
              + ", ".join(f"{v:.5f}" for v in base["fine_x_n"].values()), flush=True)
        lines.append({"test": name, "run": "dem", "seconds": wall, **base})
        for path, card in zip(args.model, cards):
            for variant in args.variants:
                rule = ({"dem_escalation": False} if variant.startswith("no ") else
                        {"release_rule": RELEASE_RULE_DRAG} if variant.startswith("drag") else {"release_rule": RELEASE_RULE})
                model = make_cell_model("ann", contact_law=law, model=Path(path), threads=1, card=card,
                                        equilibrium_corrections=20, equilibrium_tolerance=1e-4, **rule)
                if variant.startswith("released"):
                    released_to_dem(model)
                record, wall = run(model)
                row = summary(record, reference, info["p0"], cell, fine)
                print(f"  {path}, {variant}: {wall:.1f} s (load {os.getloadavg()[0]:.2f}); figure "
                      f"{100 * row['figure']:.3f} % at shear increment {row['worst_increment']} (first above 2 %: "
                      f"{row['first_above_target']}); largest q drop {100 * row['largest_q_drop']:.2f} % at "
                      f"{row['largest_q_drop_increment']}; fine grain x_n " + ", ".join(f"{v:.5f}" for v in row["fine_x_n"].values())
                      + f"; cell-increments to the DEM {row['to_dem']:.0f}; relaxed {row['relaxed']:.0f} "
                      f"({row['relaxed_substeps']:.0f} substeps, {row['relaxed_unconverged']:.0f} at the cap)", flush=True)
                lines.append({"test": name, "run": variant, "model": path, "seconds": wall, **row})
    print(f"load average after: {os.getloadavg()}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            f.writelines(json.dumps(line) + "\n" for line in lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
