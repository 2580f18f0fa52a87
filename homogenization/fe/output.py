"""Output files of a boundary-value run: curve.csv, run.h5, VTU series for ParaView, figure.

``write_outputs(directory, specimen, results, ...)`` writes, each file atomically:

- ``curve.csv``: header ``stage,eps11,eps22,sigma11,sigma22,sigma12,p,q,iterations``, one row
  per load step: specimen averages (1 = axial, the platen direction; 2 = lateral) and the
  global Newton iterations of the step; strains [-], stresses [N/m], compression positive.
- ``run.h5``: ``/mesh/{points, cells, element_alpha0_deg, gauss_points, gauss_weights}``,
  ``/history/<curve column>``, ``/history/residuals`` (n_steps, max iterations + 1; NaN
  padded) and ``/history/line_search_halvings``, ``/fields/{displacement (n_steps, n_nodes, 2), strain, stress (n_steps, n_points,
  3)}, opening, open_fraction (n_steps, n_points)}`` (Gauss points, Voigt (xx, yy, xy),
  compression positive; displacement in the FE sign, tension positive; the cells' mean opening
  angle [deg] and fraction of open contacts, NaN where the backend gives none), root attributes
  (parameters, volume rule, sign convention, provenance).
- ``vtu/step_NNNN.vtu`` and ``specimen.pvd`` (ParaView collection): displacement at the
  nodes, element averages of stress, strain, p = (s_xx + s_yy) / 2, q = s_1 - s_2, the
  deviatoric strain eps_d = sqrt((eps_xx - eps_yy)^2 + gamma_xy^2), the mean opening angle and
  the fraction of open contacts, and alpha0 per element.
- ``bvp.png``: q and eps_v against eps1 (strains in %, eps1 and eps_v counted from the end of
  the isotropic stage), and the deformed mesh coloured by eps_d; style of
  ``homogenization.output.figure_style``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import h5py
import meshio
import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from homogenization.fe.solver import BiaxialSpecimen, StepResult
from homogenization.output.figure_style import apply_style, GRID, LABELS, PNG_DPI, TickFormatter
from homogenization.material.orientation import VOLUME_RULE
from warp_hcell.core.files import atomic_write
from warp_hcell.core.provenance import provenance

CURVE_FILE = "curve.csv"
RUN_FILE = "run.h5"
PVD_FILE = "specimen.pvd"
FIGURE_FILE = "bvp.png"
VTU_FOLDER = "vtu"
FORMAT = "hmodel-bvp/1"
"""Value of the ``format`` root attribute of run.h5."""
CURVE_COLUMNS = ("stage", "eps11", "eps22", "sigma11", "sigma22", "sigma12", "p", "q", "iterations")
"""Columns of curve.csv, in order."""
SIGN_CONVENTION = "compression and contraction positive (displacements: FE sign, along +x / +y)"
SOLVER_COUNTS = {"factorisations": "sparse LU factorisations of the second-gradient Newton corrections",
                 "pivoted_factorisations": "factorisations redone with partial pivoting (the pivot-free factors "
                                           "fell short)",
                 "krylov_iterations": "preconditioned GMRES iterations of the second-gradient Newton corrections"}
"""Per-step counts of the second-gradient specimen's linear solver (``solver_counts``) written to run.h5's history."""


NOT_MATERIAL = {"line_search_halvings", "growths_taken", "tangents", "tangents_reused", *SOLVER_COUNTS}
"""Keys of ``StepResult.diagnostics`` that count the solver's work, not the backend's rules."""


def material_counts(results: Sequence[StepResult]) -> list[str]:
    """The backend's counts in the steps' diagnostics (the keys not in ``NOT_MATERIAL``), sorted."""
    return sorted({name for r in results for name in r.diagnostics} - NOT_MATERIAL)


def curve_table(results: Sequence[StepResult]) -> dict[str, np.ndarray]:
    """Columns of curve.csv as arrays (p = (s11 + s22) / 2, q = s11 - s22)."""
    table = {name: np.array([getattr(r, name) for r in results]) for name in CURVE_COLUMNS if name not in ("p", "q")}
    table["p"] = 0.5 * (table["sigma11"] + table["sigma22"])
    table["q"] = table["sigma11"] - table["sigma22"]
    return {name: table[name] for name in CURVE_COLUMNS}


def deviatoric_strain(strain: np.ndarray) -> np.ndarray:
    """eps_d = sqrt((eps_xx - eps_yy)^2 + gamma_xy^2) [-] of Voigt strains (..., 3)."""
    return np.hypot(strain[..., 0] - strain[..., 1], strain[..., 2])


def element_average(specimen: BiaxialSpecimen, values: np.ndarray) -> np.ndarray:
    """Area-weighted element averages of Gauss-point values (n_points, ...) -> (n_elements, ...)."""
    n_gauss = specimen.points_per_element()
    w = specimen.weights.reshape(-1, n_gauss)
    v = values.reshape(w.shape[0], n_gauss, *values.shape[1:])
    return np.einsum("eg,eg...->e...", w, v) / w.sum(axis=1).reshape(-1, *([1] * (values.ndim - 1)))


def _or_nan(values: np.ndarray | None, specimen: BiaxialSpecimen) -> np.ndarray:
    return np.full(specimen.n_points, np.nan) if values is None else values


def p_q(stress: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane mean stress p = (s_xx + s_yy) / 2 and deviator q = s_1 - s_2 (principal) of Voigt stresses (..., 3)."""
    return 0.5 * (stress[..., 0] + stress[..., 1]), np.hypot(stress[..., 0] - stress[..., 1], 2.0 * stress[..., 2])


def write_curve(path: Path, results: Sequence[StepResult]) -> Path:
    table = curve_table(results)
    lines = [",".join(CURVE_COLUMNS)]
    for k in range(len(results)):
        row = [str(table["stage"][k])] + [f"{float(table[n][k]):.17g}" for n in CURVE_COLUMNS[1:-1]]
        lines.append(",".join(row + [str(int(table["iterations"][k]))]))
    with atomic_write(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def write_h5(path: Path, specimen: BiaxialSpecimen, results: Sequence[StepResult], element_alpha0: np.ndarray,
             parameters: Mapping[str, Any], seed: int) -> Path:
    table = curve_table(results)
    width = max(len(r.residuals) for r in results)
    residuals = np.full((len(results), width), np.nan)
    for k, r in enumerate(results):
        residuals[k, :len(r.residuals)] = r.residuals
    with atomic_write(path) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        f.attrs["format"] = FORMAT
        f.attrs["parameters"] = json.dumps(dict(parameters), sort_keys=True)
        f.attrs["volume_rule"] = VOLUME_RULE + "; per Gauss point"
        f.attrs["sign_convention"] = SIGN_CONVENTION
        f.attrs["frames"] = "mesh (x lateral, y axial); curve 1 = axial (y), 2 = lateral (x); Voigt (xx, yy, xy) with gamma_xy"
        f.attrs["stress_units"] = "N/m (2D: force per unit length)"
        f.attrs["seed"] = int(seed)
        for key, value in provenance().items():
            f.attrs[key] = value
        mesh = f.create_group("mesh")
        mesh["points"] = specimen.mesh.p.T
        mesh["cells"] = specimen.mesh.t.T
        mesh["element_alpha0_deg"] = element_alpha0
        mesh["gauss_points"] = np.asarray(specimen.basis.global_coordinates()).reshape(2, -1).T
        mesh["gauss_weights"] = specimen.weights
        hist = f.create_group("history")
        hist["stage"] = np.asarray(table["stage"], dtype=object).astype(h5py.string_dtype())
        for name in CURVE_COLUMNS[1:]:
            hist[name] = table[name]
        hist["residuals"] = residuals
        hist["line_search_halvings"] = np.array([r.diagnostics.get("line_search_halvings", 0.0) for r in results])
        hist["line_search_halvings"].attrs["description"] = "Newton corrections halved because the residual grew"
        hist["growths_taken"] = np.array([r.diagnostics.get("growths_taken", 0.0) for r in results])
        hist["growths_taken"].attrs["description"] = "iterates taken though the residual grew (halvings exhausted)"
        for name, description in SOLVER_COUNTS.items():
            if name in results[0].diagnostics:
                hist[name] = np.array([r.diagnostics[name] for r in results])
                hist[name].attrs["description"] = description
        for name in material_counts(results):
            hist[f"material_{name}"] = np.array([r.diagnostics.get(name, 0.0) for r in results])
            hist[f"material_{name}"].attrs["description"] = f"the backend's {name} at the step's converged material update"
        hist["residuals"].attrs["description"] = "out-of-balance force norm [N/m] before each Newton iteration"
        fields = f.create_group("fields")
        fields["displacement"] = np.stack([r.displacement for r in results])
        fields["strain"] = np.stack([r.strain for r in results])
        fields["stress"] = np.stack([r.stress for r in results])
        fields["opening"] = np.stack([_or_nan(r.opening, specimen) for r in results])
        fields["open_fraction"] = np.stack([_or_nan(r.open_fraction, specimen) for r in results])
        fields["opening"].attrs["units"] = "deg"
        fields["opening"].attrs["description"] = "fabric-weighted mean opening angle of the point's cells"
        fields["open_fraction"].attrs["description"] = "fraction of the point's contacts that are open"
        fields["displacement"].attrs["units"] = "m"
        fields["strain"].attrs["units"] = "1"
        fields["stress"].attrs["units"] = "N/m"
    return path


def write_vtu(folder: Path, specimen: BiaxialSpecimen, results: Sequence[StepResult],
              element_alpha0: np.ndarray) -> Path:
    """One VTU file per load step and a ParaView collection listing them; returns the .pvd path."""
    vtu = folder / VTU_FOLDER
    vtu.mkdir(parents=True, exist_ok=True)
    points = np.column_stack([specimen.mesh.p.T, np.zeros(specimen.mesh.p.shape[1])])
    cells = [("quad", specimen.mesh.t.T)]
    entries = []
    for k, r in enumerate(results):
        strain = element_average(specimen, r.strain)
        stress = element_average(specimen, r.stress)
        p, q = p_q(stress)
        mesh = meshio.Mesh(
            points, cells,
            point_data={"displacement": np.column_stack([r.displacement, np.zeros(len(points))])},
            cell_data={"stress_xx_yy_xy": [stress], "strain_xx_yy_gxy": [strain], "p": [p], "q": [q],
                       "deviatoric_strain": [deviatoric_strain(strain)], "alpha0_deg": [element_alpha0],
                       "mean_opening_deg": [element_average(specimen, _or_nan(r.opening, specimen))],
                       "open_contact_fraction": [element_average(specimen, _or_nan(r.open_fraction, specimen))]},
        )
        name = f"step_{k + 1:04d}.vtu"
        with atomic_write(vtu / name) as tmp:
            meshio.write(tmp, mesh, file_format="vtu")
        entries.append(f'    <DataSet timestep="{k + 1}" file="{VTU_FOLDER}/{name}"/>')
    pvd = folder / PVD_FILE
    text = ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
            + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
    with atomic_write(pvd) as tmp:
        tmp.write_text(text)
    return pvd


def make_figure(specimen: BiaxialSpecimen, results: Sequence[StepResult], title: str,
                reference: Mapping[str, np.ndarray] | None = None) -> Figure:
    """q and eps_v [%] against eps1 [%] from the end of the isotropic stage; deformed mesh coloured by eps_d.

    Args:
        reference: optional material-point curve with ``eps1, q, eps_v`` [-] (same origin) to
            overlay; the one legend of the figure (first panel) then names both curves.
    """
    table = curve_table(results)
    shear = table["stage"] == "shear"
    start = np.flatnonzero(~shear)[-1] if (~shear).any() else None
    e1 = table["eps11"] - (table["eps11"][start] if start is not None else 0.0)
    ev = table["eps11"] + table["eps22"] - ((table["eps11"] + table["eps22"])[start] if start is not None else 0.0)
    fig = Figure(figsize=(12, 4.5), layout="constrained")
    ax_q, ax_v, ax_m = fig.subplots(1, 3, width_ratios=(1, 1, 0.8))
    keep = shear | (np.arange(len(results)) == start)
    ax_q.plot(100.0 * e1[keep], table["q"][keep], "-", label="finite elements")
    ax_v.plot(100.0 * e1[keep], 100.0 * ev[keep], "-", label="finite elements")
    if reference is not None:
        ax_q.plot(100.0 * reference["eps1"], reference["q"], "--", label="material point")
        ax_v.plot(100.0 * reference["eps1"], 100.0 * reference["eps_v"], "--", label="material point")
        ax_q.legend()
    ax_q.set(xlabel=LABELS["eps1"], ylabel=LABELS["q"], title="deviator")
    ax_v.set(xlabel=LABELS["eps1"], ylabel=LABELS["eps_v"], title="volumetric strain (contraction > 0)")
    last = results[-1]
    xy = specimen.mesh.p.T + last.displacement
    polys = xy[specimen.mesh.t.T]
    eps_d = deviatoric_strain(element_average(specimen, last.strain))
    collection = PolyCollection(polys, array=eps_d, cmap="viridis", edgecolors="k", linewidths=0.3)
    collection.set_clim(0.0, max(float(eps_d.max()), 1e-12))
    ax_m.add_collection(collection)
    ax_m.autoscale_view()
    ax_m.set_aspect("equal")
    ax_m.set(xlabel=LABELS["x"], ylabel=LABELS["y"], title="deformed mesh (true scale)")
    fig.colorbar(collection, ax=ax_m, label=LABELS["eps_d"], format=TickFormatter())
    for ax in (ax_q, ax_v):
        ax.grid(True, **GRID)
    fig.suptitle(title + " (compression positive)")
    return apply_style(fig)


def write_outputs(directory: Path, specimen: BiaxialSpecimen, results: Sequence[StepResult],
                  element_alpha0: np.ndarray, parameters: Mapping[str, Any], seed: int, title: str,
                  reference: Mapping[str, np.ndarray] | None = None) -> dict[str, Path]:
    """Write every output file of the run into ``directory``; returns them by kind."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {
        "curve": write_curve(directory / CURVE_FILE, results),
        "run": write_h5(directory / RUN_FILE, specimen, results, element_alpha0, parameters, seed),
        "vtu": write_vtu(directory, specimen, results, element_alpha0),
    }
    fig = make_figure(specimen, results, title, reference)
    with atomic_write(directory / FIGURE_FILE) as tmp:
        fig.savefig(tmp, format="png", dpi=PNG_DPI)
    paths["figure"] = directory / FIGURE_FILE
    return paths
