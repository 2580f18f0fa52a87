"""The sweep CLI: DEM vs analytical, fines, erosion, parallel = serial, resume, bad input."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from homogenization.output import io
from homogenization.cli import sweep
from warp_hcell.core import execution
from warp_hcell.core.cli import run_main
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import LoadingDefaults
from dask_cluster import free_port, local_cluster

P0 = 2e5
SMALL = ["--p0", "2e5", "--eps-max", "0.15", "--increment", "5e-4", "--iso-increment", "5e-4", "--orientations", "36"]
FINES = ["hcell-fines:ratio=0.3", "hcell-fines:ratio=0.6", "hcell-fines:ratio=0.76", "hcell-fines:ratio=0.82"]


def cli(argv: list[str]) -> int:
    return run_main(sweep.main, argv)


def rows_by_case(out: Path) -> dict[tuple[str, str], dict]:
    return {(r["mesostructure"], r["backend"]): r for r in sweep.read_summary(out / sweep.SUMMARY_FILE)}


@pytest.fixture(scope="module")
def fines_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "a50"
    argv = ["--mesostructure", ",".join(["hcell", *FINES]), "--alpha0", "50", "--backend", "analytical,dem",
            "--workers", "2", *SMALL, "--out", str(out)]
    assert cli(argv) == 0
    return out, argv


def test_summary_has_one_row_per_case_and_the_documented_columns(fines_sweep, capsys):
    out, _ = fines_sweep
    header = (out / sweep.SUMMARY_FILE).read_text().splitlines()[0]
    assert header.split(",")[:10] == ["mesostructure", "backend", "alpha0", "p0", "peak_q", "eps1_at_peak", "p_at_peak",
                                      "p_end", "q_end", "eps1_end"]
    rows = rows_by_case(out)
    assert set(rows) == {("hcell", "analytical"), ("hcell", "dem"), *((f, "dem") for f in FINES)}
    for row in rows.values():
        folder = out / sweep.CASES_DIR / row["case"]
        assert {p.name for p in folder.iterdir()} >= {"run.h5", "curve.csv", "cambridge.png"}
        assert row["eps1_end"] == pytest.approx(0.15, abs=1e-9) and row["alpha0"] == 50.0 and row["p0"] == P0
    stored = io.read_run(out / sweep.CASES_DIR / rows[(FINES[2], "dem")]["case"] / "run.h5")
    assert stored.attrs["parameters"]["mesostructure"] == FINES[2] and stored.attrs["parameters"]["n_grains"] == 7
    assert (out / sweep.SUMMARY_FIGURE).read_bytes()[:4] == b"\x89PNG"


def test_dem_sweep_of_the_plain_cell_reproduces_the_analytical_backend(fines_sweep):
    rows = rows_by_case(fines_sweep[0])
    dem, ana = rows[("hcell", "dem")], rows[("hcell", "analytical")]
    for name in ("peak_q", "p_end", "q_end", "p_at_5pct", "p_at_10pct"):
        assert abs(dem[name] - ana[name]) <= 0.01 * P0, name
    # issue 12 (DEM, 36 orientations): p/p0 = 0.69 at 15 % for alpha0 = 50 deg, p0 = 2e5
    assert ana["p_at_15pct"] / P0 == pytest.approx(0.69, abs=0.01)


def test_fine_grain_too_small_to_be_touched_reproduces_the_plain_cell(fines_sweep):
    rows = rows_by_case(fines_sweep[0])
    plain = rows[("hcell", "dem")]
    for fine in FINES[:2]:
        for name in ("peak_q", "p_at_5pct", "p_at_10pct", "p_end", "q_end"):
            assert abs(rows[(fine, "dem")][name] - plain[name]) <= 1e-3 * P0, (fine, name)


def test_end_pressure_grows_with_the_fine_grain_once_it_is_caught(fines_sweep):
    rows = rows_by_case(fines_sweep[0])
    p_end = [rows[(m, "dem")]["p_end"] / P0 for m in ["hcell", *FINES]]
    assert p_end[3] > p_end[2] + 0.5 and p_end[4] > 2.0 * p_end[3]
    # issue 12, measured at 36 orientations: 1.76 with 0.38 m (ratio 0.76), 11.2 with 0.41 m (ratio 0.82)
    assert p_end[3] == pytest.approx(1.76, rel=0.02) and p_end[4] == pytest.approx(11.2, rel=0.02)


def test_skipped_combinations_and_worker_count_do_not_change_results(fines_sweep, tmp_path, capsys):
    out = tmp_path / "serial"
    assert cli(["--mesostructure", f"hcell,{FINES[3]}", "--alpha0", "50", "--backend", "dem,analytical",
                "--workers", "1", *SMALL, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"skipped: analytical x {FINES[3]}: analytical models the plain H-cell only" in printed
    for row in rows_by_case(out).values():
        serial = (out / sweep.CASES_DIR / row["case"] / "curve.csv").read_bytes()
        assert serial == (fines_sweep[0] / sweep.CASES_DIR / row["case"] / "curve.csv").read_bytes()
    # resume: nothing to run; a lost case is run again, and the summary comes out the same
    summary = (out / sweep.SUMMARY_FILE).read_bytes()
    argv = ["--mesostructure", f"hcell,{FINES[3]}", "--alpha0", "50", "--backend", "dem,analytical", "--workers", "1",
            *SMALL, "--out", str(out)]
    assert cli(argv) == 0
    assert "3 cases: 3 finished before, 0 to run" in capsys.readouterr().out
    shutil.rmtree(out / sweep.CASES_DIR / rows_by_case(out)[("hcell", "analytical")]["case"])
    assert cli(argv) == 0
    assert "3 cases: 2 finished before, 1 to run" in capsys.readouterr().out
    assert (out / sweep.SUMMARY_FILE).read_bytes() == summary


def test_a_plain_h_cell_file_runs_on_the_analytical_backend_at_its_own_alpha0(tmp_path):
    meso = h_cell(55.0)
    lines = [f"cell_size = [{float(meso.cell_size[0])!r}, {float(meso.cell_size[1])!r}]", "outer = [1, 2, 3, 4, 5, 6]",
             "type1 = [[1, 2], [1, 6], [3, 4], [4, 5]]", "type2 = [[2, 3], [5, 6]]"]
    for r, (xn, xt), (dn, dt) in zip(meso.radius, meso.position, meso.driven):
        lines += ["[[grains]]", f"radius = {float(r)!r}", f"position = [{float(xn)!r}, {float(xt)!r}]",
                  f"driven = [{str(dn).lower()}, {str(dt).lower()}]"]
    path = tmp_path / "plain.toml"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "file"
    assert cli(["--mesostructure", str(path), "--alpha0", "40", "--backend", "analytical,dem", "--workers", "1", *SMALL,
                "--eps-max", "0.05", "--out", str(out)]) == 0
    rows = rows_by_case(out)
    ana, dem = rows[(str(path), "analytical")], rows[(str(path), "dem")]
    assert ana["alpha0"] == pytest.approx(55.0, abs=1e-9)
    assert abs(ana["p_end"] - dem["p_end"]) <= 1e-3 * P0 and abs(ana["q_end"] - dem["q_end"]) <= 1e-3 * P0


def test_erosion_removes_the_fine_grain_and_the_plain_response_comes_back(fines_sweep, tmp_path):
    out = tmp_path / "erode"
    assert cli(["--mesostructure", "hcell,hcell-fines:ratio=0.8", "--alpha0", "50", "--backend", "dem", "--workers", "1",
                "--erode-at", "0.05", *SMALL, "--out", str(out)]) == 0
    rows = rows_by_case(out)
    plain, eroded = rows[("hcell", "dem")], rows[("hcell-fines:ratio=0.8", "dem")]
    assert np.isnan(plain["erode_at"]) and eroded["erode_at"] == 0.05
    record = io.read_run(out / sweep.CASES_DIR / eroded["case"] / "run.h5").record
    assert list(dict.fromkeys(record.stage)) == ["iso", "shear", "erode", "eroded"]
    before = record.p[record.stage == "shear"][-1]
    at = record.p[record.stage == "erode"][0]
    assert before > 1.5 * plain["p_at_5pct"] and abs(at - plain["p_at_5pct"]) <= 1e-2 * P0
    assert abs(eroded["p_end"] - plain["p_end"]) <= 1e-3 * P0
    assert record.eps11[-1] - record.eps11[record.stage == "iso"][-1] == pytest.approx(0.15, abs=1e-9)
    assert eroded["n_unconverged"] == 0.0


def test_changed_options_on_an_existing_sweep_are_refused(fines_sweep, capsys):
    out, argv = fines_sweep
    changed = [a if a != "0.15" else "0.1" for a in argv]
    assert cli(changed) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds a run with other eps_max; pass --overwrite or choose another --out" in err


@pytest.mark.parametrize("args, message", [
    (["--mesostructure", "hcell-fines:ratio=0.85", "--alpha0", "50,55"],
     "fine grain ratio 0.85 does not fit the pore at n=0, t=0: the largest is 0.829562 (alpha0 = 50 deg)"),
    (["--mesostructure", "hcell:size=2"], "unknown key 'size' for hcell"),
    (["--backend", "dem,fem"], "unknown backend 'fem'"),
    (["--alpha0", "50,20"], "alpha0 = 20 deg is outside [30, 90) deg"),
    (["--erode-at", "0.2", "--mesostructure", "hcell-fines:ratio=0.5"], "--erode-at 0.2 must be below --eps-max 0.15"),
    (["--model", "x.pt"], "--model applies to --backend ann only"),
    (["--mesostructure", "hcell3d:alpha0=55"], "a 3D cell; a sweep runs biaxial tests of planar cells"),
    (["--eps-max", "5"], "--eps-max: 5 is outside (0, 1)"),
    (["--backend", "ann", "--model", "missing.pt"], "--model missing.pt: no such model file"),
])
def test_bad_input_is_one_line_and_exit_2_before_any_work(tmp_path, capsys, args, message):
    """Values argparse checks end in its usage line plus one error line; the rest is one line."""
    out = tmp_path / "bad"
    try:
        code = cli([*SMALL, *args, "--out", str(out)])
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1] and (len(err) == 1 or err[0].startswith("usage:"))
    assert not out.exists()


def test_an_overwrite_interrupted_while_writing_a_case_leaves_its_old_folder_whole(tmp_path, monkeypatch):
    """A case's folder is written as a unit: an --overwrite run stopped while drawing a case's figure (its run.h5
    and curve.csv written) leaves the old case whole, which the next --overwrite run recomputes; before, the new
    run.h5 and curve.csv sat beside the old figure and counted as finished."""
    out = tmp_path / "s"
    argv = ["--mesostructure", "hcell", "--alpha0", "50", "--backend", "analytical", "--workers", "1", *SMALL,
            "--out", str(out)]
    assert cli([*argv, "--eps-max", "0.01"]) == 0
    folder = next((out / sweep.CASES_DIR).iterdir())
    old = {name: (folder / name).read_bytes() for name in ("run.h5", "curve.csv", sweep.FIGURE_FILE)}

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    with monkeypatch.context() as patch:
        patch.setattr(sweep.figures, "save_figure", interrupted)
        assert cli([*argv, "--eps-max", "0.02", "--overwrite"]) == 130
    assert {name: (folder / name).read_bytes() for name in old} == old
    assert sorted(p.name for p in folder.parent.iterdir()) == [folder.name]
    assert cli([*argv, "--eps-max", "0.02", "--overwrite"]) == 0
    assert io.read_run(folder / "run.h5").attrs["parameters"]["eps_max"] == 0.02
    assert (folder / sweep.FIGURE_FILE).read_bytes() != old[sweep.FIGURE_FILE]


def test_a_foreign_non_empty_folder_is_not_touched(tmp_path, capsys):
    out = tmp_path / "other"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert cli([*SMALL, "--out", str(out)]) == 2
    assert "exists; pass --overwrite to replace it" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.slow
def test_study_resolution_reproduces_the_documented_table(tmp_path):
    """docs/gap_graded.md, alpha0 = 55, p0 = 2e5, 72 orientations, 1e-4: p/p0 at 15 % = 0.123, 2.115, 18.004."""
    out = tmp_path / "study"
    assert cli(["--mesostructure", "hcell,hcell-fines:ratio=0.8,hcell-fines:ratio=0.9", "--alpha0", "55", "--p0", "2e5",
                "--eps-max", "0.15", "--increment", "1e-4", "--iso-increment", "1e-4", "--orientations", "72",
                "--workers", "2", "--out", str(out)]) == 0
    rows = rows_by_case(out)
    for meso, expected in (("hcell", 0.123), ("hcell-fines:ratio=0.8", 2.115), ("hcell-fines:ratio=0.9", 18.004)):
        assert rows[(meso, "dem")]["p_at_15pct"] / P0 == pytest.approx(expected, abs=0.001)


def test_drained_sweep_with_erosion_holds_sigma22(tmp_path):
    """The caught fine grain is removed at 5 %; sigma22 stays at p0 through the removal (to the
    driver's default stress tolerance)."""
    out = tmp_path / "drained"
    assert cli(["--mesostructure", "hcell-fines:ratio=0.8", "--alpha0", "50", "--p0", "2e5", "--drained",
                "--eps-max", "0.1", "--erode-at", "0.05", "--increment", "1e-3", "--iso-increment", "5e-4",
                "--orientations", "24", "--out", str(out)]) == 0
    row = next(iter(rows_by_case(out).values()))
    record = io.read_run(out / sweep.CASES_DIR / row["case"] / "run.h5").record
    after_iso = record.stage != "iso"
    assert set(record.stage[after_iso]) == {"shear", "erode", "eroded"}
    # the isotropic stage lands p within the tolerance, shear moves sigma22 from there to P0
    assert np.abs(record.sigma22[after_iso] / P0 - 1.0).max() <= 2.0 * LoadingDefaults.stress_rtol
    assert row["eps1_end"] == pytest.approx(0.1, abs=1e-9)
    assert record.p[record.stage == "erode"][0] < record.p[record.stage == "shear"][-1]  # the grain carried load


# -- ANN cases: one model per mesostructure ------------------------------------------------------
ANN_FINES = ("hcell-fines:alpha0=50,ratio=0.76", "hcell-fines:alpha0=50,ratio=0.82")
ANN_SMALL = ["--p0", "2e5", "--eps-max", "0.01", "--increment", "1e-3", "--iso-increment", "1e-3", "--orientations", "4"]


@pytest.fixture(scope="module")
def fines_models(tmp_path_factory):
    """Tiny models (a few epochs on a small DEM database) of the two cells: plumbing, not physics."""
    from dem_database import build
    from training.train import main as train_main
    from warp_hcell.mesostructures.builders import resolve_mesostructure

    models = {}
    for k, spec in enumerate(ANN_FINES):
        folder = tmp_path_factory.mktemp(f"fines_model{k}")
        db = build(folder / "db.h5", mesostructure=resolve_mesostructure(spec), precompression=(0.0, 2e-3),
                   n_directions=6, spacing=1e-2, leg_length=0.04, threads=1)
        assert train_main(["--data", str(db), "--out", str(folder / "m.pt"), "--epochs", "2", "--hidden", "8",
                           "--threads", "1", "--no-rollout"]) == 0
        models[spec] = folder / "m.pt"
    return models


def _models_used(out: Path) -> dict[str, str]:
    return {r["mesostructure"]: io.read_run(out / sweep.CASES_DIR / r["case"] / "run.h5").attrs["parameters"]
            ["backend_options"]["model"] for r in sweep.read_summary(out / sweep.SUMMARY_FILE) if r["backend"] == "ann"}


def test_each_fines_cell_runs_on_the_model_of_its_mesostructure(fines_models, tmp_path):
    """Bare --model items are matched by the mesostructure hash they record, whatever their order;
    a MESOSTRUCTURE=PATH item names the model of one cell."""
    first, second = (fines_models[spec] for spec in ANN_FINES)
    out = tmp_path / "bare"
    assert cli(["--mesostructure", ",".join(ANN_FINES), "--backend", "ann,dem", "--workers", "1", "--model", str(second),
                "--model", str(first), "--uncertified-ok", *ANN_SMALL, "--out", str(out)]) == 0
    assert _models_used(out) == {ANN_FINES[0]: str(first), ANN_FINES[1]: str(second)}
    rows = sweep.read_summary(out / sweep.SUMMARY_FILE)
    assert len(rows) == 4 and all(np.isfinite(r["p_end"]) and r["p_end"] > 0 for r in rows)
    keyed = tmp_path / "keyed"
    assert cli(["--mesostructure", ANN_FINES[1], "--backend", "ann", "--model", f"{ANN_FINES[1]}={second}",
                "--uncertified-ok", *ANN_SMALL, "--out", str(keyed)]) == 0
    assert _models_used(keyed) == {ANN_FINES[1]: str(second)}
    assert (keyed / sweep.SUMMARY_FILE).read_text().splitlines()[1] == \
        next(line for line in (out / sweep.SUMMARY_FILE).read_text().splitlines() if ANN_FINES[1] in line and ",ann," in line)


@pytest.mark.parametrize("models, message", [
    (lambda m: [str(m[ANN_FINES[0]])], f"no ANN model for mesostructure {ANN_FINES[1]}"),
    (lambda m: [f"{ANN_FINES[1]}={m[ANN_FINES[0]]}", str(m[ANN_FINES[0]])], "was trained on mesostructure"),
    (lambda m: [f"hcell-fines:ratio=0.5={m[ANN_FINES[0]]}"], "hcell-fines:ratio=0.5 is not one of --mesostructure"),
])
def test_a_fines_cell_without_its_model_is_one_line_and_exit_2(fines_models, tmp_path, capsys, models, message):
    out = tmp_path / "bad"
    argv = ["--mesostructure", ",".join(ANN_FINES), "--backend", "ann"]
    for item in models(fines_models):
        argv += ["--model", item]
    assert cli([*argv, *ANN_SMALL, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists()


def test_a_bare_model_of_other_grains_is_refused_for_the_plain_cell_before_any_case(fines_models, tmp_path, capsys):
    """The plain H-cell runs on the single bare --model whatever its alpha0; a model of a cell with other grains
    (here a fines cell's) failed inside the run (exit 1) instead."""
    from homogenization.ann import default_model_path

    out = tmp_path / "plain"
    argv = ["--mesostructure", "hcell", "--backend", "ann", "--uncertified-ok", *ANN_SMALL, "--out", str(out)]
    assert cli([*argv, "--model", str(fines_models[ANN_FINES[0]])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"is a model of {ANN_FINES[0]}, whose grains differ from those of hcell:" in err[0], err
    assert not out.exists()
    assert cli([*argv, "--alpha0", "50", "--model", str(default_model_path())]) == 0  # the H-cell's model: any alpha0


# -- execution: in process, local Dask cluster, remote scheduler ----------------------------------
TINY = ["--mesostructure", "hcell,hcell-fines:ratio=0.8", "--alpha0", "50,55", "--p0", "2e5", "--eps-max", "0.03",
        "--increment", "1e-3", "--iso-increment", "1e-3", "--orientations", "8"]


def test_unreachable_scheduler_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(execution, "CONNECT_TIMEOUT_S", 1.0)
    out = tmp_path / "remote"
    assert cli([*TINY, "--scheduler", f"tcp://127.0.0.1:{free_port()}", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot reach the Dask scheduler at tcp://127.0.0.1:" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_a_remote_scheduler_gives_the_in_process_results(tmp_path):
    """A real scheduler and two workers on 127.0.0.1, started in another folder (they write
    nothing: the client writes every file); the summary and every curve are byte-identical to
    the in-process sweep."""
    local, short = tmp_path / "local", [*TINY, "--eps-max", "0.01"]  # (the cluster's start-up is most of the time)
    assert cli([*short, "--workers", "1", "--out", str(local)]) == 0
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    elsewhere = tmp_path / "workers"
    elsewhere.mkdir()
    with local_cluster(2, env, cwd=elsewhere) as (address, _):
        remote = tmp_path / "remote"
        assert cli([*short, "--scheduler", address, "--out", str(remote)]) == 0
    assert (remote / sweep.SUMMARY_FILE).read_bytes() == (local / sweep.SUMMARY_FILE).read_bytes()
    rows = sweep.read_summary(local / sweep.SUMMARY_FILE)
    assert len(rows) == 4
    for row in rows:
        curve = Path(sweep.CASES_DIR) / row["case"] / io.CURVE_FILE
        assert (remote / curve).read_bytes() == (local / curve).read_bytes()
    assert [p.name for p in elsewhere.iterdir() if not p.name.startswith("dask-scratch")] == []


def test_an_ann_case_records_its_models_certificate_in_run_h5(fines_models, tmp_path):
    """As biaxial does (parameters' ``ann_model``): sha256, certificate worst, certified, the
    problem; a certified copy of the model records its passed certificate (and a case folder of
    the uncertified model is then another run: refused without --overwrite)."""
    import json

    from homogenization.learning import certificate as certification
    from homogenization.ann.records import Certificate
    from homogenization.ann import default_model_path
    from warp_hcell.core.provenance import file_sha256

    spec = ANN_FINES[0]
    model = tmp_path / "m.pt"
    shutil.copy(fines_models[spec], model)
    shutil.copy(fines_models[spec].with_suffix(".json"), model.with_suffix(".json"))
    argv = ["--mesostructure", spec, "--backend", "ann", "--model", str(model), *ANN_SMALL]
    out = tmp_path / "s"
    assert cli([*argv, "--uncertified-ok", "--out", str(out)]) == 0
    (row,) = sweep.read_summary(out / sweep.SUMMARY_FILE)
    stored = io.read_run(out / sweep.CASES_DIR / row["case"] / "run.h5").attrs["parameters"]["ann_model"]
    assert stored["sha256"] == file_sha256(model) and stored["certified"] is False
    assert stored["certificate_worst"] is None and "uncertified" in stored["certificate_problem"]
    full = json.loads(default_model_path().with_suffix(".json").read_text())["certificate"]  # meets the minimum
    certification.write_certificate(model, Certificate.from_dict({**full, "model_sha256": file_sha256(model), "passed": True,
                                                                  "worst": 0.0123, "worst_test": "x", "target": 0.02}))
    assert cli([*argv, "--out", str(tmp_path / "c")]) == 0
    (row,) = sweep.read_summary(tmp_path / "c" / sweep.SUMMARY_FILE)
    stored = io.read_run(tmp_path / "c" / sweep.CASES_DIR / row["case"] / "run.h5").attrs["parameters"]["ann_model"]
    assert stored["certified"] is True and stored["certificate_worst"] == 0.0123 and stored["certificate_problem"] is None
    assert cli([*argv, "--out", str(out)]) == 2


def test_a_second_sweep_on_a_busy_folder_exits_2(tmp_path, capsys):
    from warp_hcell.core.files import output_lock

    out = tmp_path / "s"
    with output_lock(out):
        assert cli(["--backend", "analytical", *SMALL, "--out", str(out)]) == 2
    assert "is being written by another run" in capsys.readouterr().err


def test_a_case_of_an_edited_mesostructure_file_runs_again(tmp_path, capsys):
    """A case's identity holds its cell's geometry (the description's sha256), not only the file's name: an edited
    file is a case with other parameters (refused without --overwrite), not a finished one."""
    meso = tmp_path / "cell.toml"
    h_cell_file = Path(__file__).resolve().parents[1] / "warp_hcell" / "data" / "h_cell_fine_grain.toml"
    meso.write_text(h_cell_file.read_text())
    argv = ["--mesostructure", str(meso), "--backend", "dem", "--workers", "1", "--p0", "2e5", "--eps-max", "0.004",
            "--increment", "1e-3", "--orientations", "6", "--out", str(tmp_path / "s")]
    assert cli(argv) == 0
    text = meso.read_text()
    assert "radius = 0.26091387708279157" in text
    meso.write_text(text.replace("radius = 0.26091387708279157", "radius = 0.25"))  # a smaller, free fine grain
    assert cli(argv) == 2
    assert "holds a run with other mesostructure_sha256" in capsys.readouterr().err


def test_the_summary_counts_the_rules_that_fired():
    """summary.csv had n_unconverged only: the closed form's n_alpha_limit and the ANN's out-of-distribution
    counts never reached it."""
    from types import SimpleNamespace

    from homogenization.sweeps.case import fired_counts

    nan = float("nan")
    record = SimpleNamespace(diagnostics={"n_alpha_limit": np.array([1.0, 2.0, nan]), "n_unconverged": np.ones(3),
                                          "n_ood": np.zeros(3), "n_alpha_limit_all_calls": np.ones(3) * 5,
                                          "substeps": np.ones(3)})
    assert fired_counts(record) == "n_alpha_limit=3"
    assert "counts" in sweep.SUMMARY_COLUMNS


def test_a_warning_inside_a_case_is_one_line_naming_the_case(tmp_path, capsys, monkeypatch):
    """A case's warnings came out of a worker in Python's two-line form, naming no case."""
    import warnings

    from homogenization.sweeps import case as case_module

    real = case_module.compute_case

    def warning(case):
        warnings.warn("something\n  fired", RuntimeWarning)
        return real(case)
    monkeypatch.setattr(case_module, "compute_case", warning)
    out = tmp_path / "s"
    assert cli(["--backend", "analytical", "--workers", "1", *SMALL, "--eps-max", "0.01", "--out", str(out)]) == 0
    folder = next((out / sweep.CASES_DIR).iterdir()).name
    assert [line for line in capsys.readouterr().err.splitlines() if "warning" in line] == [
        f"warning: {folder}: something fired"]


def test_a_rerun_with_fewer_cases_says_which_folders_its_summary_leaves_out(tmp_path, capsys):
    out = tmp_path / "s"
    argv = ["--backend", "analytical", "--workers", "1", *SMALL, "--eps-max", "0.005", "--out", str(out)]
    assert cli([*argv, "--alpha0", "50,55"]) == 0
    capsys.readouterr()
    assert cli([*argv, "--alpha0", "55"]) == 0
    assert "1 case folder(s) of other settings in" in capsys.readouterr().out
    assert len((out / sweep.SUMMARY_FILE).read_text().splitlines()) == 2
