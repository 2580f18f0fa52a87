"""Legend labels and figure titles of runs, from the metadata each run stores (never its folder).

``describe(parameters, ...)`` turns the ``parameters`` attribute of a run file (the dict that
``hmodel biaxial``, the sweep and the boundary-value command write) into named parts of text:
the test, backend, mesostructure (short name), alpha0, p0 and number of orientations, then
the erosion, fabric, increment and contact law. ``split_labels`` sorts the parts of several
runs: a part equal in every run goes into the title (one part of each kind, so a title never
names only some of the runs), a part that differs into each run's legend label. Example:
three runs that differ only in backend get the labels "analytical", "DEM", "ANN" and the title
"constant-volume biaxial test, H-cell, $\\alpha_0$ = 55°, $p_0 = 2\\times10^{5}$ N/m, $N$ = 360".
Numbers are mathtext (``figure_style.number``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

from homogenization.output.figure_style import number
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.builders import parse_mesostructure
from warp_hcell.mesostructures.mesostructure import MesostructureError

BACKEND_NAMES = {"analytical": "analytical", "dem": "DEM", "ann": "ANN"}
"""Display names of the backends (others are shown as registered)."""
TITLE_KEYS = ("test", "backend", "mesostructure", "alpha0", "p0", "n_orientations", "erosion", "fabric")
"""Parts that go into the title when every run has the same one."""
LEGEND_ONLY_KEYS = ("increment", "kn", "kt_over_kn", "phi_g", "radius")
"""Parts shown only where they tell runs apart (never in a title)."""
KEYS = TITLE_KEYS + LEGEND_ONLY_KEYS
"""Every part, in the order they are written."""


def mesostructure_name(text: str | None) -> str:
    """Short name of the mesostructure a run names (``parameters["mesostructure"]``).

    None (the plain H-cell of --alpha0) and ``hcell`` specs give "H-cell"; ``hcell-unequal``
    and ``hcell-fines`` specs add the lateral and fine-grain radii over r; a file gives its
    stem. alpha0 is a part of its own and never in this name.
    """
    if text is None:
        return "H-cell"
    try:
        source = parse_mesostructure(text)
    except MesostructureError:  # a file that is not here any more
        return Path(text).stem
    if source.kind is None:
        return Path(text).stem
    options = dict(source.options)
    details = []
    if options.get("lateral", 1.0) != 1.0:
        details.append(f"$r_l/r$ = {options['lateral']:g}")
    ratio = tuple(r for r in options.get("ratio", ()) if r > 0.0)  # type: ignore[union-attr]
    if ratio:
        details.append("fines $r_f/r$ = " + "/".join(f"{r:g}" for r in ratio))
    return "H-cell" + (f" ({'; '.join(details)})" if details else "")


def _given(parameters: Mapping[str, Any], key: str, fallback: Any) -> Any:
    """``parameters[key]`` if the run stores the key (even as None), else ``fallback``."""
    return parameters[key] if key in parameters else fallback


def ann_mark(ann_model: Mapping[str, Any] | None) -> str:
    """What a figure says after "ANN" of a run its certificate does not cover: " (uncertified)" or
    " (outside its certificate's envelope)"; "" for a certified run inside it or any other backend."""
    if not ann_model:
        return ""
    if ann_model.get("certified") is False:
        return " (uncertified)"
    return " (outside its certificate's envelope)" if ann_model.get("outside_envelope") else ""


def describe(parameters: Mapping[str, Any], *, test: str = "", backend: str | None = None,
             alpha0_deg: float | None = None, n_orientations: int | None = None, dim: int = 2) -> dict[str, str]:
    """Parts of text (``KEYS`` -> text, "" where it does not apply) describing one run.

    Args:
        parameters: the run's stored parameters (``backend``, ``mesostructure``,
            ``alpha0_deg``, ``p0`` [N/m], ``n_orientations``, ``erode_at`` [-],
            ``fabric_anisotropy``, ``increment`` [-], ``contact_law``, ``radius`` [m], ``ann_model``:
            an ANN run uncertified or outside its certificate's envelope is marked, ``ann_mark``).
        test: what the run is, e.g. "constant-volume biaxial test".
        backend, alpha0_deg, n_orientations: used where ``parameters`` lacks the key.
        dim: the run's dimension: stresses (p0) in N/m for 2, Pa for 3.
    """
    backend = _given(parameters, "backend", backend)
    alpha0 = _given(parameters, "alpha0_deg", alpha0_deg)
    p0 = parameters.get("p0")
    n = _given(parameters, "n_orientations", n_orientations)
    erode_at = parameters.get("erode_at")
    fabric = parameters.get("fabric_anisotropy") or 0.0
    increment = parameters.get("increment")
    law = parameters.get("contact_law") or {}
    radius = parameters.get("radius")
    parts = {
        "test": test,
        "backend": (BACKEND_NAMES.get(backend, str(backend)) + ann_mark(parameters.get("ann_model"))) if backend else "",
        "mesostructure": mesostructure_name(parameters.get("mesostructure")),
        "alpha0": f"$\\alpha_0$ = {alpha0:g}°" if alpha0 is not None and math.isfinite(alpha0) else "",
        "p0": f"$p_0 = {number(p0)}$ {dimension(dim).stress_unit}" if p0 else "",
        "n_orientations": f"$N$ = {int(n)}" if n else "",
        "erosion": f"fines removed at $\\varepsilon_1$ = {100 * erode_at:g} %" if erode_at is not None else "",
        "fabric": f"$a_f$ = {fabric:g}" if fabric else "",
        "increment": f"$\\Delta\\varepsilon = {number(increment)}$" if increment else "",
        "kn": f"$k_n = {number(law['kn'])}$ N/m" if "kn" in law else "",
        "kt_over_kn": f"$k_t/k_n$ = {law['kt_over_kn']:g}" if "kt_over_kn" in law else "",
        "phi_g": f"$\\varphi_g$ = {law['phi_g_deg']:g}°" if "phi_g_deg" in law else "",
        "radius": f"$r$ = {radius:g} m" if radius else "",
    }
    return {key: parts[key] for key in KEYS}


def title(parts: Mapping[str, str]) -> str:
    """Title of one run: its ``TITLE_KEYS`` parts, comma separated."""
    return ", ".join(parts[key] for key in TITLE_KEYS if parts.get(key))


def split_labels(descriptions: Sequence[Mapping[str, str]]) -> tuple[str, list[str]]:
    """(title, legend label of each run) of runs described by ``describe``.

    The title holds the ``TITLE_KEYS`` parts that are equal (and not empty) in every run; a
    label holds the parts that differ between runs, so a single run gets the label "".
    Runs whose labels would be equal or empty are told apart by "run 1", "run 2", ... (their
    order).
    """
    differ = [key for key in KEYS if len({d.get(key, "") for d in descriptions}) > 1]
    common = {key: descriptions[0].get(key, "") for key in TITLE_KEYS if key not in differ}
    labels = [", ".join(d[key] for key in differ if d.get(key)) for d in descriptions]
    if len(descriptions) > 1 and (len(set(labels)) < len(labels) or "" in labels):
        labels = [f"{label}, run {k + 1}" if label else f"run {k + 1}" for k, label in enumerate(labels)]
    return title(common), labels
