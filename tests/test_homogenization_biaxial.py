"""The biaxial CLI: tiny end-to-end runs with a physical end check, errors, overwrite, overlay."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_checks import assert_usage_error

from homogenization.cli import biaxial
from homogenization.output import io
from homogenization.backends import BACKENDS
from warp_hcell.core.cli import cuda_device_count, run_main
from warp_hcell.core.parameters import LoadingDefaults

TINY = ["--alpha0", "55", "--p0", "5.85e6", "--eps-max", "0.05", "--increment", "5e-4", "--iso-increment", "1e-4",
        "--orientations", "24"]
P0 = 5.85e6


def cli(argv: list[str]) -> int:
    return run_main(biaxial.main, argv)


def last_curve_row(path: Path) -> dict[str, str]:
    with open(path) as fh:
        return list(csv.DictReader(fh))[-1]


def test_constant_volume_run_ends_on_the_reference_curve(tmp_path, capsys):
    out = tmp_path / "cv"
    assert cli(TINY + ["--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"-> {out / 'run.h5'}, {out / 'curve.csv'}" in printed and f"figure -> {out / 'cambridge.png'}" in printed
    row = last_curve_row(out / "curve.csv")
    assert row["stage"] == "shear"
    # docs/model.md, "Reference response", alpha0 = 55, p0 = 5.85e6, eps1 = 5 %: p/p0 = 0.937, q/p0 = 0.573
    assert float(row["p"]) / P0 == pytest.approx(0.937, abs=0.005)
    assert float(row["q"]) / P0 == pytest.approx(0.573, abs=0.005)
    stored = io.read_run(out / "run.h5")
    assert stored.attrs["parameters"]["alpha0_deg"] == 55.0 and stored.attrs["parameters"]["n_orientations"] == 24
    assert stored.record.p[stored.record.stage == "iso"][-1] == pytest.approx(P0, rel=LoadingDefaults.stress_rtol)
    assert (out / "cambridge.png").read_bytes()[:4] == b"\x89PNG"


def test_drained_run_holds_sigma22(tmp_path):
    out = tmp_path / "drained"
    assert cli(TINY + ["--drained", "--deviator", "t", "--fourth-panel", "W2", "--out", str(out)]) == 0
    stored = io.read_run(out / "run.h5").record
    shear = stored.stage == "shear"
    # the isotropic stage lands p within the tolerance, shear moves sigma22 from there to P0
    assert np.abs(stored.sigma22[shear] / P0 - 1.0).max() <= 2.0 * LoadingDefaults.stress_rtol
    assert stored.sigma11[shear][-1] > 1.5 * P0


def test_fabric_weights_reach_the_run(tmp_path):
    out = tmp_path / "fabric"
    assert cli(TINY + ["--fabric-anisotropy", "0.3", "--fabric-direction", "90", "--eps-max", "0.01", "--out", str(out)]) == 0
    stored = io.read_run(out / "run.h5")
    w = stored.record.weights
    assert w.sum() == pytest.approx(1.0) and w[0] == pytest.approx((1 - 0.3) / 24)  # theta = 0 is 90 deg off b_f
    assert stored.attrs["parameters"]["fabric_anisotropy"] == 0.3
    iso = stored.record.stage == "iso"
    assert stored.record.q[iso][-1] < -1e-3 * P0  # more cells along 22: stiffer in 22 under isotropic strain


def test_existing_output_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli(TINY + ["--out", str(out)]) == 0
    before = (out / "curve.csv").read_bytes()
    capsys.readouterr()
    assert cli(TINY + ["--p0", "2e5", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == f"hmodel: error: {out} exists; pass --overwrite to replace it"
    assert (out / "curve.csv").read_bytes() == before
    assert cli(TINY + ["--p0", "2e5", "--overwrite", "--out", str(out)]) == 0
    assert float(last_curve_row(out / "curve.csv")["p"]) < 0.5 * 2e5  # the low-pressure run replaced it


def test_comma_list_overlays_backends(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(BACKENDS, "elastic", "cell_doubles:ElasticCell")
    out = tmp_path / "both"
    assert cli(TINY + ["--backend", "analytical,elastic", "--out", str(out)]) == 0
    for name in ("analytical", "elastic"):
        assert io.read_run(out / name / "run.h5").record.backend == name
        assert (out / name / "curve.csv").is_file()
    assert not (out / "run.h5").exists()
    assert sorted(p.name for p in out.iterdir()) == ["analytical", "cambridge.png", "elastic"]
    assert capsys.readouterr().out.count(" increments in ") == 2


@pytest.mark.parametrize("extra, message", [
    (["--backend", "analytical,foo"], "argument --backend: unknown backend 'foo'; choose from analytical, dem, ann"),
    (["--alpha0", "25"], "argument --alpha0: alpha0 = 25 deg is outside [30, 90) deg"),
    (["--alpha0", "90"], "argument --alpha0: alpha0 = 90 deg is outside [30, 90) deg"),
    (["--p0", "0"], "argument --p0: 0 must be > 0"),
    (["--p0=-5e5"], "argument --p0: -5e5 must be > 0"),
    (["--orientations", "0"], "argument --orientations: 0 must be >= 1"),
    (["--fabric-anisotropy", "1"], "argument --fabric-anisotropy: 1 is outside [0, 1)"),
])
def test_bad_arguments_one_line_exit_2(tmp_path, capsys, extra, message):
    assert_usage_error(capsys, cli, TINY + extra + ["--out", str(tmp_path / "x")], message, tmp_path / "x")


def test_inconsistent_options_one_line_exit_2(tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setitem(BACKENDS, "ghost", "homogenization.backends.ghost:GhostCell")
    cases = [
        (["--threads", "4", "--out", str(tmp_path / "a")], "--threads applies to --backend dem or ann only"),
        (["--model", "m.pt", "--out", str(tmp_path / "a")], "--model applies to --backend ann only"),
        (["--device", "cuda", "--out", str(tmp_path / "a")],
         "--device applies to --backend dem or ann only (analytical runs on the cpu)" if cuda_device_count()
         else "--device cuda: no CUDA GPU on this machine; use --device cpu"),
        (["--backend", "ghost", "--out", str(tmp_path / "a")], "backend 'ghost' is not available in this version"),
        (["--out", str(blocker / "sub")], f"cannot write to {blocker / 'sub'}: {blocker} is not a folder"),
        (["--mesostructure", "hcell-fines:ratio=0.5", "--out", str(tmp_path / "a")],
         "analytical: analytical models the plain H-cell only (six equal touching grains); mesostructure "
         "'hcell-fines:ratio=0.5' is not one: use --backend dem or ann"),
        (["--mesostructure", "hcell:radius=1", "--out", str(tmp_path / "a")],
         "analytical: mesostructure 'hcell:radius=1' has grains of radius 1 m, the analytical cell 0.5 m (--radius)"),
    ]
    for extra, message in cases:
        assert cli(TINY + extra) == 2
        assert capsys.readouterr().err.strip() == f"hmodel: error: {message}"
    assert not (tmp_path / "a").exists()


def test_real_process_exit_code_and_help(tmp_path):
    env = {**os.environ, "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", "homogenization.biaxial"]
    bad = subprocess.run(cmd + ["--alpha0", "95", "--out", str(tmp_path / "x")], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines()[-1].endswith("error: argument --alpha0: alpha0 = 95 deg is outside [30, 90) deg")
    helped = subprocess.run(cmd + ["--help"], capture_output=True, text=True, env=env)
    assert helped.returncode == 0 and "--eps-max" in helped.stdout and "(default: 1e-05)" in helped.stdout


def test_module_docstring_starts_with_the_command():
    assert biaxial.__doc__.splitlines()[0].startswith("hmodel biaxial --backend analytical --alpha0 55")


def test_every_backend_is_built_before_any_run(tmp_path, capsys):
    out = tmp_path / "both"
    assert cli(TINY + ["--backend", "analytical,ann", "--model", str(tmp_path / "missing.pt"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hmodel: error: ") and "\n" not in err and "missing.pt" in err
    assert not out.exists()  # the analytical run did not start


def test_analytical_and_dem_overlay_agree(tmp_path):
    pytest.importorskip("warp")
    out = tmp_path / "overlay"
    argv = ["--backend", "analytical,dem", "--alpha0", "55", "--p0", "2e5", "--eps-max", "0.01", "--increment", "1e-3",
            "--iso-increment", "1e-4", "--orientations", "12", "--out", str(out)]
    assert cli(argv) == 0
    a, d = (io.read_run(out / name / "run.h5").record for name in ("analytical", "dem"))
    assert np.array_equal(a.stage, d.stage)
    # the README's DEM figure at 2e5 is 2.1e-4 of p0; this short run measures 2.2e-5 / 3.1e-4 (p / q)
    assert np.abs(a.p - d.p).max() <= 6e-4 * 2e5 and np.abs(a.q - d.q).max() <= 6e-4 * 2e5
    assert d.diagnostics["substeps"].shape == (d.n_increments,) and d.diagnostics["n_unconverged"].sum() == 0


def test_ann_model_of_another_mesostructure_is_refused(tmp_path, capsys):
    """The shipped model is trained on H-cells: a cell with smaller lateral grains is refused
    before any work, in one line, exit 2."""
    out = tmp_path / "run"
    lateral = Path(__file__).resolve().parents[1] / "warp_hcell" / "data" / "h_cell_lateral_0.7D.toml"
    argv = ["--backend", "ann", "--mesostructure", str(lateral), "--orientations", "12",
            "--eps-max", "0.01", "--increment", "1e-3", "--out", str(out)]
    assert run_main(biaxial.main, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model trained on mesostructure" in err[0] and "lateral grains" in err[0]
    assert not out.exists()
