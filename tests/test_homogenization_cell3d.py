"""3D cells outside the triaxial command: ``hmodel cell`` on a path of three columns, the 3D
Python API of docs/usage.md, the analytical backend built for the other dimension, and the
opening angle of a ten-sphere H-cell through a description and a file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.backends.analytical import Analytical3DCell
from homogenization.cli import hmodel
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.files import describe, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import build_h_cell_3d, h_cell, plain_alpha0_3d

ROOT = Path(__file__).resolve().parents[1]
ROWS = [(1e-4, -2e-5, 0.0)] * 60 + [(0.0, 1e-4, -1e-4)] * 30 + [(-5e-5, 0.0, 2e-5)] * 20
"""Axial compression, then lateral shear between t1 and t2, then partial unloading [-]."""


def write_path(path: Path, rows=ROWS, header: str = "d_eps_n,d_eps_t1,d_eps_t2") -> Path:
    path.write_text(header + "\n" + "".join(",".join(repr(v) for v in row) + "\n" for row in rows))
    return path


def read_table(path: Path) -> tuple[list[str], np.ndarray]:
    header = path.read_text().splitlines()[0].split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def driven_directly(alpha0: float) -> dict[str, np.ndarray]:
    """Every observable of the analytical 3D backend after each row of ``ROWS``, stepped here."""
    model = Analytical3DCell(ContactLaw(), 0.5)
    state = model.init_state(build_h_cell_3d(alpha0), 1)
    history: dict[str, list[float]] = {}
    for row in ROWS:
        state, _ = model.step(state, np.array([row]))
        for name, value in model.observables(state).items():
            history.setdefault(name, []).append(float(value[0]))
    return {name: np.array(values) for name, values in history.items()}


def test_hmodel_cell_drives_a_3d_cell_as_the_analytical_3d_backend(tmp_path, capsys):
    path = write_path(tmp_path / "path.csv")
    out = tmp_path / "cell.csv"
    assert hmodel.main(["cell", "--mesostructure", "hcell3d:alpha0=57.5", "--path", str(path), "--out", str(out),
                        "--positions"]) == 0, capsys.readouterr().err
    header, table = read_table(out)
    assert header[:5] == ["l1", "l2", "l3", "alpha_deg_a", "d1_a"] and "S_t2t2" in header and header[-1] == "x_t210"
    assert len(header) == 18 + 30 and table.shape == (len(ROWS), len(header))
    expected = driven_directly(57.5)
    for k, name in enumerate(header):
        np.testing.assert_array_equal(table[:, k], expected[name], err_msg=name)
    assert np.ptp(expected["S_t1t1"] - expected["S_t2t2"]) > 0.0  # t1 and t2 were driven apart


def test_a_three_column_path_defaults_to_the_ten_sphere_cell_at_alpha0(tmp_path, capsys):
    path = write_path(tmp_path / "path.csv")
    for name, extra in (("spec", ["--mesostructure", "hcell3d:alpha0=60"]), ("default", ["--alpha0", "60"])):
        assert hmodel.main(["cell", *extra, "--path", str(path), "--out", str(tmp_path / f"{name}.csv")]) == 0
    assert (tmp_path / "spec.csv").read_bytes() == (tmp_path / "default.csv").read_bytes()


def test_the_dem_backend_on_the_same_3d_path(tmp_path, capsys):
    pytest.importorskip("warp")
    path = write_path(tmp_path / "path.csv")
    tables = {}
    for backend in ("analytical", "dem"):
        out = tmp_path / f"{backend}.csv"
        assert hmodel.main(["cell", "--backend", backend, "--mesostructure", "hcell3d:alpha0=55", "--path", str(path),
                            "--out", str(out)]) == 0, capsys.readouterr().err
        tables[backend] = read_table(out)
    header, dem = tables["dem"]
    assert header == ["l1", "l2", "l3", "S_nn", "S_t1t1", "S_t2t2"]
    analytical_header, analytical = tables["analytical"]
    for k, name in enumerate(header):
        reference = analytical[:, analytical_header.index(name)]
        assert np.abs(dem[:, k] - reference).max() <= 1e-3 * np.abs(reference).max(), name


@pytest.mark.parametrize("header, spec, message", [
    ("d_eps_n,d_eps_t1,d_eps_t2", "hcell:alpha0=55", "a path of 3 columns (d_eps_n,d_eps_t1,d_eps_t2) but "
     "--mesostructure hcell:alpha0=55 is a planar cell, whose path has the header d_eps_n,d_eps_t"),
    ("d_eps_n,d_eps_t", "hcell3d:alpha0=55", "a path of 2 columns (d_eps_n,d_eps_t) but --mesostructure "
     "hcell3d:alpha0=55 is a 3D cell, whose path has the header d_eps_n,d_eps_t1,d_eps_t2"),
])
def test_a_path_of_the_other_dimension_is_one_line(header, spec, message, tmp_path, capsys):
    rows = [row[:len(header.split(","))] for row in ROWS]
    path = write_path(tmp_path / "path.csv", rows, header)
    out = tmp_path / "cell.csv"
    out.write_text("kept")
    assert hmodel.main(["cell", "--mesostructure", spec, "--path", str(path), "--out", str(out), "--overwrite"]) == 2
    assert capsys.readouterr().err == f"hmodel cell: error: {path}: {message}\n"
    assert out.read_text() == "kept" and sorted(p.name for p in tmp_path.iterdir()) == ["cell.csv", "path.csv"]


def test_a_row_of_three_numbers_is_needed(tmp_path, capsys):
    path = write_path(tmp_path / "path.csv", [(1e-4, 0.0, 0.0), (1e-4, 0.0)])
    assert hmodel.main(["cell", "--path", str(path), "--out", str(tmp_path / "cell.csv")]) == 2
    assert capsys.readouterr().err == (f"hmodel cell: error: {path} line 3: expected three numbers "
                                       f"d_eps_n,d_eps_t1,d_eps_t2, got '0.0001,0.0'\n")


def test_the_analytical_backend_of_the_other_dimension_says_which_dim_to_pass():
    with pytest.raises(ValueError, match=r"is a 3D cell and this analytical backend models 2D cells: build the "
                                         r"backend with make_cell_model\('analytical', dim=3\)"):
        make_cell_model("analytical").init_state(build_h_cell_3d(55.0), 1)
    with pytest.raises(ValueError, match=r"is a 2D cell .* models 3D cells: .*dim=2\)"):
        make_cell_model("analytical", dim=3).init_state(h_cell(55.0), 1)


def h3_file(tmp_path: Path, meso, labels: bool) -> Path:
    """``meso`` written as a mesostructure TOML file (with its H-cell labels if ``labels``)."""
    from warp_hcell.mesostructures.hcell import H3_TYPE1_PAIRS, H3_TYPE2_PAIRS

    lines = ["name = 'ten spheres'", f"cell_size = {[float(v) for v in meso.cell_size]}",
             f"outer = {(meso.outer + 1).tolist()}"]
    if labels:
        lines += [f"type1 = {[list(p) for p in H3_TYPE1_PAIRS]}", f"type2 = {[list(p) for p in H3_TYPE2_PAIRS]}"]
    for r, x, d in zip(meso.radius, meso.position, meso.driven):
        lines += ["[[grains]]", f"radius = {float(r)!r}", f"position = [{', '.join(repr(float(v)) for v in x)}]",
                  f"driven = [{', '.join('true' if v else 'false' for v in d)}]"]
    path = tmp_path / ("labelled.toml" if labels else "plain.toml")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("alpha0", [45.0, 55.0, 62.123456789, 89.0])
def test_alpha0_of_a_ten_sphere_cell_survives_its_description_and_a_file(alpha0, tmp_path):
    built = build_h_cell_3d(alpha0)
    for again in (from_description(describe(built)), load_mesostructure(h3_file(tmp_path, built, labels=True))):
        assert again.parameters == {"alpha0_deg": alpha0} and plain_alpha0_3d(again) == (alpha0, 0.5)
        model = make_cell_model("analytical", dim=3)
        responses = [model.step(model.init_state(cell, 1), np.array([ROWS[0]]))[1].moment for cell in (built, again)]
        np.testing.assert_array_equal(*responses)
    assert load_mesostructure(h3_file(tmp_path, built, labels=False)).parameters == {}  # no labels: no H-cell


def test_the_3d_example_of_the_usage_page_runs():
    text = (ROOT / "docs" / "usage.md").read_text()
    block = text.split("### 3D cells", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    namespace: dict = {}
    exec(compile(block, "docs/usage.md", "exec"), namespace)  # noqa: S102 (the page's own example)
    record, response = namespace["record"], namespace["response"]
    assert response.moment.shape == (1, 3, 3) and np.all(np.diag(response.moment[0]) > 0.0)
    assert record.p.size > 10 and np.all(np.isfinite(record.q)) and record.sigma33 is not None
