"""Legend labels and titles from run metadata: short names, the split into title and legend."""

from __future__ import annotations

import pytest

from homogenization.output import run_labels

BASE = {"backend": "dem", "mesostructure": None, "alpha0_deg": 55.0, "p0": 2e5, "n_orientations": 360,
        "contact_law": {"kn": 2e8, "kt_over_kn": 0.5, "phi_g_deg": 30.0}, "radius": 0.5, "increment": 1e-4}


@pytest.mark.parametrize("text, name", [
    (None, "H-cell"), ("hcell", "H-cell"), ("hcell:alpha0=50,radius=0.25", "H-cell"),
    ("hcell-unequal:lateral=0.7", "H-cell ($r_l/r$ = 0.7)"),
    ("hcell-fines:ratio=0.76", "H-cell (fines $r_f/r$ = 0.76)"),
    ("hcell-fines:ratio=0.3/0.3,n=0.4/-0.4,lateral=0.8", "H-cell ($r_l/r$ = 0.8; fines $r_f/r$ = 0.3/0.3)"),
    ("some/folder/h_cell_lateral_0.7D.toml", "h_cell_lateral_0.7D"),  # a file (gone or not): its stem
])
def test_mesostructure_short_names(text, name):
    assert run_labels.mesostructure_name(text) == name


def test_describe_writes_mathtext_parts():
    parts = run_labels.describe(BASE, test="constant-volume biaxial test")
    assert parts["backend"] == "DEM" and parts["mesostructure"] == "H-cell"
    assert parts["alpha0"] == r"$\alpha_0$ = 55°" and parts["p0"] == r"$p_0 = 2\times10^{5}$ N/m"
    assert parts["n_orientations"] == "$N$ = 360" and parts["erosion"] == "" and parts["fabric"] == ""
    assert run_labels.title(parts) == (r"constant-volume biaxial test, DEM, H-cell, $\alpha_0$ = 55°, "
                                       r"$p_0 = 2\times10^{5}$ N/m, $N$ = 360")


def test_describe_falls_back_on_the_record_and_skips_what_a_run_lacks():
    parts = run_labels.describe({}, backend="ann", alpha0_deg=40.0, n_orientations=12)
    assert (parts["backend"], parts["alpha0"], parts["n_orientations"], parts["p0"]) == ("ANN", r"$\alpha_0$ = 40°",
                                                                                       "$N$ = 12", "")
    # a stored alpha0 of None (a cell without H-cell labels) wins over the record's NaN
    assert run_labels.describe({"alpha0_deg": None}, alpha0_deg=55.0)["alpha0"] == ""
    assert run_labels.describe({}, alpha0_deg=float("nan"))["alpha0"] == ""


def test_split_puts_shared_parts_in_the_title_and_differences_in_the_labels():
    runs = [BASE, BASE | {"backend": "ann"}, BASE | {"backend": "analytical", "p0": 5.85e6}]
    title, labels = run_labels.split_labels([run_labels.describe(r, test="test") for r in runs])
    assert labels == [r"DEM, $p_0 = 2\times10^{5}$ N/m", r"ANN, $p_0 = 2\times10^{5}$ N/m",
                      r"analytical, $p_0 = 5.85\times10^{6}$ N/m"]
    assert title == r"test, H-cell, $\alpha_0$ = 55°, $N$ = 360"


def test_legend_only_parts_never_reach_the_title():
    runs = [BASE, BASE | {"increment": 1e-5, "contact_law": BASE["contact_law"] | {"phi_g_deg": 20.0}}]
    title, labels = run_labels.split_labels([run_labels.describe(r) for r in runs])
    assert labels == [r"$\Delta\varepsilon = 10^{-4}$, $\varphi_g$ = 30°",
                      r"$\Delta\varepsilon = 10^{-5}$, $\varphi_g$ = 20°"]
    assert title == r"DEM, H-cell, $\alpha_0$ = 55°, $p_0 = 2\times10^{5}$ N/m, $N$ = 360"
    title, labels = run_labels.split_labels([run_labels.describe(BASE)])
    assert labels == [""] and "varepsilon" not in title and "k_n" not in title


def test_equal_or_empty_labels_are_numbered():
    assert run_labels.split_labels([run_labels.describe(BASE)] * 2)[1] == ["run 1", "run 2"]
    eroded = BASE | {"erode_at": 0.05}
    assert run_labels.split_labels([run_labels.describe(r) for r in (eroded, BASE)])[1] == [
        r"fines removed at $\varepsilon_1$ = 5 %, run 1", "run 2"]


def test_an_ann_run_its_certificate_does_not_cover_is_marked():
    from homogenization.output.run_labels import describe

    inside = {"backend": "ann", "ann_model": {"certified": True, "outside_envelope": []}}
    outside = {"backend": "ann", "ann_model": {"certified": True, "outside_envelope": ["p0 above 1e6"]}}
    uncertified = {"backend": "ann", "ann_model": {"certified": False, "outside_envelope": None}}
    assert describe(inside)["backend"] == "ANN"
    assert describe(outside)["backend"] == "ANN (outside its certificate's envelope)"
    assert describe(uncertified)["backend"] == "ANN (uncertified)"
    assert describe({"backend": "dem"})["backend"] == "DEM"
