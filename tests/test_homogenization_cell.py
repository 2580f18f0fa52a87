"""Element-test CLI ``python -m homogenization.cell``: end-to-end runs and bad input."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from homogenization.cli import cell
from homogenization.backends import BACKENDS
from warp_hcell.core.cli import run_main
from warp_hcell.core.parameters import ContactLaw

MU = ContactLaw().mu
HEADER = "l1,l2,alpha_deg,d1,d2,N1,N2,T1,S_nn,S_tt"
POSITIONS = ",".join(f"x_n{i},x_t{i}" for i in range(1, 7))


def _write_path(path: Path, rows, header="d_eps_n,d_eps_t") -> Path:
    path.write_text(header + "\n" + "".join(f"{row}\n" for row in rows))
    return path


def _compression(tmp_path, n=300, name="path.csv"):
    """Axial compression at constant width, 1e-5 per increment."""
    return _write_path(tmp_path / name, ["1e-5,0"] * n)


def _run(argv, capsys):
    code = run_main(cell.main, [str(a) for a in argv])
    return code, capsys.readouterr().err


def _read(path):
    header = path.read_text().splitlines()[0]
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def test_docstring_starts_with_the_command():
    assert cell.__doc__.splitlines()[0].startswith("python -m homogenization.cell --backend analytical")


def test_axial_compression_end_to_end(tmp_path, capsys):
    out = tmp_path / "out.csv"
    code, err = _run(["--alpha0", 55, "--path", _compression(tmp_path), "--out", out, "--positions"], capsys)
    assert code == 0 and err == ""
    header, table = _read(out)
    assert header == HEADER + "," + POSITIONS
    assert table.shape == (300, 22)
    col = {name: table[:, i] for i, name in enumerate(header.split(","))}
    a0 = np.radians(55.0)
    np.testing.assert_allclose(col["l1"][-1], (1 + 2 * np.cos(a0)) * (1 - 1e-5) ** 300, rtol=1e-14)
    np.testing.assert_allclose(col["l2"], 2 * np.sin(a0), rtol=1e-14)
    # a loose cell compressed along its axis at constant width slides, alpha opening
    assert np.all(np.diff(col["alpha_deg"]) > 0)
    np.testing.assert_allclose(col["T1"], MU * col["N1"], rtol=1e-12)
    a = np.radians(col["alpha_deg"])
    F1 = 2 * (col["N1"] * np.cos(a) + col["T1"] * np.sin(a))
    np.testing.assert_allclose(col["S_nn"], F1 * col["l1"], rtol=1e-9, atol=1e-9 * ContactLaw().kn * 0.5)
    np.testing.assert_allclose(col["x_n1"] - col["x_n4"], col["l1"], rtol=1e-14)


def test_module_runs_as_a_script(tmp_path):
    out = tmp_path / "out.csv"
    path = _compression(tmp_path, n=20)
    result = subprocess.run(
        [sys.executable, "-m", "homogenization.cell", "--alpha0", "40", "--path", str(path), "--out", str(out)],
        capture_output=True, text=True, cwd=Path(__file__).parents[1],
    )
    assert result.returncode == 0, result.stderr
    header, table = _read(out)
    assert header == HEADER and table.shape == (20, 10) and np.all(table[:, 5] > 0)


def test_kt_defaults_to_kt_over_kn_times_kn(tmp_path, capsys):
    path = _compression(tmp_path, n=50)
    law = ContactLaw(kn=1e8)
    outputs = {}
    for name, extra in [("default", []), ("same", ["--kt", law.kt]), ("other", ["--kt", 0.2 * law.kn])]:
        outputs[name] = tmp_path / f"{name}.csv"
        code, _ = _run(["--kn", 1e8, "--alpha0", 40, "--path", path, "--out", outputs[name], *extra], capsys)
        assert code == 0
    assert outputs["default"].read_text() == outputs["same"].read_text()
    assert outputs["default"].read_text() != outputs["other"].read_text()


@pytest.mark.parametrize(
    "rows, header, message",
    [
        ([], "d_eps_n,d_eps_t", ": no increments after the header"),
        (["1e-5,0"], "d_eps_t,d_eps_n", ": header must be 'd_eps_n,d_eps_t' (a planar cell) or "
                                         "'d_eps_n,d_eps_t1,d_eps_t2' (a 3D cell), got 'd_eps_t,d_eps_n'"),
        (["1e-5,0", "", "1e-5,0"], "d_eps_n,d_eps_t", " line 3: expected two numbers d_eps_n,d_eps_t, got ''"),
        (["1e-5,0,0"], "d_eps_n,d_eps_t", " line 2: expected two numbers d_eps_n,d_eps_t, got '1e-5,0,0'"),
        (["1e-5,abc"], "d_eps_n,d_eps_t", " line 2: expected two numbers d_eps_n,d_eps_t, got '1e-5,abc'"),
        (["1e-5,0", "nan,0"], "d_eps_n,d_eps_t", " line 3: increments must be finite and in (-1, 1), got 'nan,0'"),
        (["1e-5,inf"], "d_eps_n,d_eps_t", " line 2: increments must be finite and in (-1, 1), got '1e-5,inf'"),
        (["1.5,0"], "d_eps_n,d_eps_t", " line 2: increments must be finite and in (-1, 1), got '1.5,0'"),
    ],
)
def test_bad_path_file(tmp_path, capsys, rows, header, message):
    path = _write_path(tmp_path / "bad.csv", rows, header)
    out = tmp_path / "out.csv"
    code, err = _run(["--path", path, "--out", out], capsys)
    assert code == 2
    assert err == f"hmodel: error: {path}{message}\n"
    assert not out.exists()


def test_missing_path_file(tmp_path, capsys):
    code, err = _run(["--path", tmp_path / "none.csv", "--out", tmp_path / "out.csv"], capsys)
    assert code == 2 and err == f"hmodel: error: path file {tmp_path / 'none.csv'} does not exist\n"


@pytest.mark.parametrize("alpha0", ["29", "90", "nan", "abc"])
def test_bad_alpha0(tmp_path, capsys, alpha0):
    with pytest.raises(SystemExit) as exc:
        cell.main(["--alpha0", alpha0, "--path", str(_compression(tmp_path)), "--out", str(tmp_path / "o.csv")])
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("python -m homogenization.cell: error: argument --alpha0: ")
    assert "outside [30, 90) deg" in last or "not a number" in last or "not finite" in last


def test_existing_output_is_protected(tmp_path, capsys):
    out = tmp_path / "out.csv"
    out.write_text("precious\n")
    path = _compression(tmp_path, n=5)
    code, err = _run(["--path", path, "--out", out], capsys)
    assert code == 2 and err == f"hmodel: error: {out} exists; pass --overwrite to replace it\n"
    assert out.read_text() == "precious\n"
    code, _ = _run(["--path", path, "--out", out, "--overwrite"], capsys)
    assert code == 0 and out.read_text().startswith(HEADER + "\n")


def test_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    path = _compression(tmp_path, n=5)
    code, err = _run(["--path", path, "--out", blocker / "out.csv"], capsys)
    assert code == 2 and err == f"hmodel: error: cannot write to {blocker / 'out.csv'}: {blocker} is not a folder\n"
    code, err = _run(["--path", path, "--out", tmp_path], capsys)
    assert code == 2 and err == f"hmodel: error: --out {tmp_path} is a folder; give a file name\n"
    assert blocker.read_text() == "x"


def test_options_of_other_backends_and_unavailable_backends(tmp_path, capsys, monkeypatch):
    path = _compression(tmp_path, n=5)
    out = tmp_path / "out.csv"
    code, err = _run(["--path", path, "--out", out, "--mesostructure", "hcell-fines:ratio=0.5"], capsys)
    assert code == 2 and err.startswith("hmodel: error: analytical models the plain H-cell only") and err.count("\n") == 1
    code, err = _run(["--path", path, "--out", out, "--phi", 95], capsys)
    assert code == 2 and err == "hmodel: error: phi_g = 95 deg is outside [0, 90) deg\n"
    monkeypatch.setitem(BACKENDS, "future", "homogenization.backends.not_written_yet:FutureCell")
    code, err = _run(["--backend", "future", "--path", path, "--out", out], capsys)
    assert code == 2 and err == "hmodel: error: backend 'future' is not available in this version\n"
    assert not out.exists()


def test_dem_backend_through_the_same_cli(tmp_path, capsys):
    pytest.importorskip("warp")
    if "dem" not in BACKENDS:
        pytest.skip("no dem backend registered")
    path = _compression(tmp_path, n=40)
    tables = {}
    for backend in ("analytical", "dem"):
        out = tmp_path / f"{backend}.csv"
        code, err = _run(["--backend", backend, "--alpha0", 55, "--path", path, "--out", out], capsys)
        if backend == "dem" and "not available" in err:
            pytest.skip("dem backend module not there yet")
        assert code == 0, err
        tables[backend] = _read(out)
    assert tables["dem"][0] == tables["analytical"][0] == HEADER
    dem, ana = tables["dem"][1], tables["analytical"][1]
    forces = slice(5, 8)  # N1, N2, T1
    assert np.abs(dem[:, forces] - ana[:, forces]).max() <= 1e-3 * np.abs(ana[:, forces]).max()


def test_the_backends_counts_are_said_in_the_status_line(tmp_path, capsys, monkeypatch):
    """A rule that fires in a step (an ``n_*`` diagnostic) is summed over the increments and said; it was dropped."""
    real = cell.make_cell_model

    class Counting:
        def __init__(self, model):
            self.model = model

        def __getattr__(self, name):
            return getattr(self.model, name)

        def step(self, state, d_eps):
            state, response = self.model.step(state, d_eps)
            response.diagnostics["n_fired"] = 1.0
            return state, response

    monkeypatch.setattr(cell, "make_cell_model", lambda *a, **k: Counting(real(*a, **k)))
    out = tmp_path / "out.csv"
    assert run_main(cell.main, ["--path", str(_compression(tmp_path, n=3)), "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"analytical: 3 increments -> {out} (counts over the increments: n_fired 3)"


def test_a_builder_spec_is_built_at_the_radius_given(tmp_path, capsys):
    """--mesostructure hcell --radius 0.25 ran the DEM on 0.5 m grains (the spec's default), silently."""
    out = tmp_path / "out.csv"
    code, err = _run(["--backend", "dem", "--mesostructure", "hcell", "--radius", 0.25, "--alpha0", 55,
                      "--path", _compression(tmp_path, n=1), "--out", out], capsys)
    assert code == 0
    header, table = _read(out)
    l1 = table[0, header.split(",").index("l1")]
    np.testing.assert_allclose(l1, 2 * 0.25 * (1 + 2 * np.cos(np.radians(55.0))) * (1 - 1e-5), rtol=1e-6)


@pytest.mark.parametrize("spec, warned", [("hcell:alpha0=50", True), ("hcell", False),
                                          (str(Path(cell.__file__).parents[2] / "warp_hcell" / "data" /
                                               "h_cell_fine_grain.toml"), True)])
def test_an_alpha0_the_cell_does_not_take_is_said(spec, warned, tmp_path, capsys, recwarn):
    """A spec with its own alpha0, or a file, ran at its own angle whatever --alpha0 said, silently."""
    out = tmp_path / "out.csv"
    code, _ = _run(["--backend", "dem", "--mesostructure", spec, "--alpha0", 35, "--path", _compression(tmp_path, n=1),
                    "--out", out], capsys)
    said = [str(w.message) for w in recwarn if "--alpha0 is not used" in str(w.message)]
    assert code == 0 and len(said) == int(warned), said
    assert all(message.endswith("gives its own opening angle") for message in said)
