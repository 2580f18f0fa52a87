"""python studies/diagnose_hybrid_paths.py --model M.pt --mesostructure SPEC [--test drained] [--escalation on|off]

Where and why the 3D hybrid meso-ANN (the network, then K exact equilibrium corrections) leaves the
DEM, cell by cell, on one triaxial test (p0, to --eps-max at --increment, the Lebedev rule --order x
--spins): both backends run the test; at every distinct start state the free-DOF coordinates of
every cell are kept, and the script prints

- the cells whose free grains depart from the DEM's by more than --threshold [m], with the increment
  where each does (cells come in pairs where two spins see the same cell);
- for the first departing cells, the increments around the onset of the departure (--onset): the DOF
  that departs, the DEM's
  and the hybrid's move of it over the increment [um], and the hybrid's force ratios (the network's
  guess, after the corrections) and Newton steps;
- from the DEM's own state at the onset of the first departing cell: the DEM's increment, the network's alone and the
  hybrid's, of that cell's most-moved free grain [um] (whether the corrections moved it at all); then, under the
  hybrid's one-increment contact law (``training.equilibrium.balance``), the force ratio of the DEM's end and where
  the corrections land with the diagonal stiffness of their Newton matrix set to each of --regularisations (the
  package's: ``training.fast_equilibrium3d.REGULARISATION``): several balanced ends far apart are equilibria
  that the exact law does not tell apart.

Strains [-], compression positive; DOFs numbered as the model's free_dofs (0-based).
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

from warp_hcell.core.cli import Parser, positive_float, positive_int


class _Keeper:
    """A cell model that passes every call to ``model`` and keeps, per distinct start state, the free-DOF
    coordinates of that state (``free_of``), the last call's step input, and the hybrid's correction counts."""

    def __init__(self, model, free_of, corrections_of=None) -> None:
        self.model, self.name, self.free_of, self.corrections_of = model, model.name, free_of, corrections_of
        self.last = None
        self.free, self.inputs, self.ratios = [], [], []

    def __getattr__(self, name):
        return getattr(self.model, name)

    def step(self, state, d_eps, *, with_tangent=False):
        new, response = self.model.step(state, d_eps, with_tangent=with_tangent)
        if state is not self.last:
            self.last = state
            self.free.append(self.free_of(state))
            self.inputs.append(None)
            self.ratios.append(None)
        self.inputs[-1] = (state, np.array(d_eps))
        counts = self.corrections_of() if self.corrections_of is not None else None
        if counts is not None:
            self.ratios[-1] = np.stack([counts.force_ratio[0], counts.force_ratio[1], counts.steps])
        return new, response


def main(argv=None) -> int:
    parser = Parser(description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a 3D meso-ANN model (.pt)")
    parser.add_argument("--mesostructure", required=True, help="the cell (a builder spec or a file)")
    parser.add_argument("--test", choices=("undrained", "drained"), default="drained")
    parser.add_argument("--p0", type=positive_float, default=2e5, help="isotropic pressure [Pa]")
    parser.add_argument("--eps-max", type=positive_float, default=0.15, help="axial strain of the shear stage [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--order", type=positive_int, default=11, help="Lebedev order of the cell axes")
    parser.add_argument("--spins", type=positive_int, default=4, help="spins per axis")
    parser.add_argument("--corrections", type=positive_int, default=20, help="K, the most Newton steps")
    parser.add_argument("--tolerance", type=positive_float, default=1e-4, help="force ratio of the corrections")
    parser.add_argument("--escalation", choices=("on", "off"), default="on",
                        help="the hybrid hands the cells with a released grain to the DEM (on) or not")
    parser.add_argument("--threshold", type=positive_float, default=1e-3, help="departure of a free DOF [m]")
    parser.add_argument("--onset", type=positive_float, default=1e-5,
                        help="the departure [m] whose increment is shown in detail (the onset)")
    parser.add_argument("--shown", type=positive_int, default=4, help="departing cells shown in detail")
    parser.add_argument("--regularisations", default="1e-9,1e-5,1e-4,1e-3,1e-2",
                        help="comma-separated diagonal stiffnesses of the Newton matrix, fractions of kn [-]")
    args = parser.parse_args(argv)

    from homogenization.backends import make_cell_model
    from homogenization.ann.cell import AnnCell3D, AnnState
    from homogenization.element_test import driver, programme as programmes
    from warp_hcell.core.parameters import ContactLaw
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(args.mesostructure).build(None)
    hybrid = AnnCell3D(ContactLaw(), 0.5, model=args.model, equilibrium_corrections=args.corrections,
                       equilibrium_tolerance=args.tolerance, dem_escalation=args.escalation == "on")
    alone = AnnCell3D(ContactLaw(), 0.5, model=args.model, equilibrium_corrections=0)
    free_dofs = hybrid.net.schema.free_dofs.cpu().numpy()
    dem_model = make_cell_model("dem", dim=3, threads=1)
    dem_free = lambda s: dem_model.state_to_arrays(s)["position"][:, free_dofs[:, 0], free_dofs[:, 1]]  # noqa: E731
    dem = _Keeper(dem_model, dem_free)
    ann = _Keeper(hybrid, lambda s: np.array(s.free_position), hybrid.fast.last_corrections)
    programme = programmes.triaxial(args.p0, args.eps_max, args.increment, test=args.test,
                                 iso_increment=0.5 * args.increment)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for keeper in (dem, ann):
            driver.run(keeper, programme, mesostructure=meso, lebedev_order=args.order, n_spins=args.spins,
                       progress=False)
    n = min(len(dem.free), len(ann.free))
    x_dem, x_ann = np.stack(dem.free[:n]), np.stack(ann.free[:n])
    off = np.abs(x_ann - x_dem).max(axis=2)
    departed = np.flatnonzero((off > args.threshold).any(axis=0))
    first = {int(c): int(np.argmax(off[:, c] > args.threshold)) for c in departed}
    print(f"{args.mesostructure}, {args.test}, p0 = {args.p0:g} Pa, to {args.eps_max:g} at {args.increment:g}, "
          f"{off.shape[1]} cells, hybrid K = {args.corrections} at {args.tolerance:g}, escalation {args.escalation}")
    print(f"cells whose free grains depart by more than {args.threshold:g} m: {departed.size} of {off.shape[1]}; "
          f"first increments: {sorted(first.values())}")
    for c in sorted(first, key=first.get)[:args.shown]:
        start = int(np.argmax(off[:, c] > args.onset)) - 1  # the increment that took it past the onset
        k = int(np.argmax(np.abs(x_ann[start + 1, c] - x_dem[start + 1, c])))
        print(f"cell {c}: off by {args.onset:g} m after increment {start}, by {args.threshold:g} m from {first[c]}; "
              f"DOF {k}:")
        for i in range(max(start - 1, 0), min(start + 4, n - 1)):
            ratios = ann.ratios[i]
            counts = "" if ratios is None else (f"  force ratio {ratios[0, c]:.2g} -> {ratios[1, c]:.2g}, "
                                                f"{int(ratios[2, c])} Newton steps")
            print(f"  increment {i}: DEM moves it {1e6 * (x_dem[i + 1, c, k] - x_dem[i, c, k]):+9.3f} um, "
                  f"the hybrid {1e6 * (x_ann[i + 1, c, k] - x_ann[i, c, k]):+9.3f} um{counts}")
    if first:
        c = min(first, key=first.get)
        i = int(np.argmax(off[:, c] > args.onset)) - 1
        state, d_eps = dem.inputs[i]
        arrays = dem_model.state_to_arrays(state)
        learning = AnnState(arrays["cell_size"], dem_free(state), arrays["shear_force"])
        after_dem = dem_free(dem_model.step(state, d_eps)[0])
        moves = {"DEM": after_dem, "network alone": alone.step(learning, d_eps)[0].free_position,
                 "hybrid": hybrid.step(learning, d_eps)[0].free_position}
        grain = free_dofs[int(np.argmax(np.abs(after_dem[c] - learning.free_position[c]))), 0]
        cols = np.flatnonzero(free_dofs[:, 0] == grain)
        print(f"from the DEM's state of increment {i}, cell {c}, grain {grain} (DOFs {cols.tolist()}), its move [um]:")
        for name, after in moves.items():
            print(f"  {name:>13}: {np.array2string(1e6 * (after[c, cols] - learning.free_position[c, cols]), precision=3)}")
        _landings(hybrid, learning, d_eps, after_dem, c, cols, args)
    return 0


def _landings(hybrid, learning, d_eps, after_dem, c, cols, args) -> None:
    """Print the force ratio, under the one-increment contact law, of the DEM's end of cell ``c`` and of the
    corrections' ends at each of ``args.regularisations``, with the move of DOFs ``cols`` [um]."""
    import torch

    from training.equilibrium import balance, corrected_advance
    from training.network import features_and_contacts

    net = hybrid.net
    size, free, shear, strain = (torch.as_tensor(np.asarray(a, dtype=np.float64)[c:c + 1]) for a in
                                 (learning.cell_size, learning.free_position, learning.shear_force, d_eps))
    old = features_and_contacts(net.schema, net.active_index, size, free, shear, strain, net.load_features)[3]
    ends = {"DEM": torch.as_tensor(after_dem[c:c + 1]) - free}
    with torch.no_grad():
        for text in args.regularisations.split(","):
            out = corrected_advance(net, size, free, shear, strain, args.corrections, args.tolerance,
                                    regularisation=float(text))
            ends[f"corrections at {float(text):g} kn ({int(out.corrections[0])} steps)"] = (
                out.increment.free_position - free)
        print("under the one-increment contact law: force ratio at the end, and the move [um]:")
        for name, d in ends.items():
            residual, fn_max = balance(net.schema, size, free, shear, strain, d, old)
            print(f"  {name:>34}: {float(residual.abs().max() / fn_max.max()):.2e}  "
                  f"{np.array2string(1e6 * d[0, cols].numpy(), precision=3)}")


if __name__ == "__main__":
    raise SystemExit(main())
