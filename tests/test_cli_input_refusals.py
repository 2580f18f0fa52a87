"""Bad input that an audit of the commands found reaching long work or a traceback: each is refused in one line,
exit code 2, before any work, and leaves nothing behind."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_checks import assert_one_line_refusal

from homogenization.ann import default_model_path
from homogenization.cli import biaxial, bvp, calibrate, certify, learn
from training import train as train_command
from warp_hcell import generate

UNDRAINED = "# test = undrained\n# p0 = 3e6\n"


@pytest.mark.parametrize("main, argv, expected", [
    (learn.main, ["--mesostructure", "hcell:alpha0=55", "--eps-max", "5"], "--eps-max: 5 is outside (0, 1)"),
    (bvp.main, ["--eps-max", "5"], "--eps-max: 5 is outside (0, 1)"),
    (biaxial.main, ["--eps-max", "1"], "--eps-max: 1 is outside (0, 1)"),
    (biaxial.main, ["--mesostructure", "hcell3d:alpha0=55"], "a 3D cell; hmodel biaxial runs planar cells"),
    (biaxial.main, ["--increment", "1e-12"], "into 2e+11 increments, more than 1e+07"),
    (bvp.main, ["--increment", "1e-12"], "into 5e+10 increments, more than 1e+07"),
], ids=["learn eps-max", "bvp eps-max", "biaxial eps-max", "biaxial 3D cell", "biaxial increment", "bvp increment"])
def test_a_run_command_refuses_at_once(main, argv, expected, tmp_path, capsys):
    assert_one_line_refusal(capsys, main, [*argv, "--out", str(tmp_path / "out")], expected, tmp_path / "out")


@pytest.mark.parametrize("data, prior, expected", [
    ("eps1,q,eps_v\n0.004,1.1e6,0\n0.008,1.8e6,0\n", None, "column eps_v is 0 throughout"),
    ("eps1,q\n0.004,1.1e6\n0.008,1.8e6\n", '{"phi_g": [10, 95]}', "phi_g = 95 deg is outside [0, 90) deg"),
    ("eps1,q\n0.004,1.1e6\n0.008,1.8e6\n", '{"kt_over_kn": [-1, 1]}', "kt_over_kn = -1 must be finite and > 0"),
], ids=["flat column", "phi_g prior", "kt/kn prior"])
def test_calibrate_refuses_data_and_priors_it_cannot_run(data, prior, expected, tmp_path, capsys):
    (tmp_path / "u.csv").write_text(UNDRAINED + data)
    argv = ["--data", str(tmp_path / "u.csv"), "--params", "phi_g" if prior is None or "phi_g" in prior else "kt_over_kn"]
    if prior is not None:
        (tmp_path / "prior.json").write_text(prior)
        argv += ["--prior", str(tmp_path / "prior.json")]
    assert_one_line_refusal(capsys, calibrate.main, [*argv, "--out", str(tmp_path / "cal")], expected, tmp_path / "cal")


def test_generate_refuses_a_precompression_no_path_reaches_and_leaves_no_sidecar(tmp_path, capsys):
    out = tmp_path / "db.h5"
    assert_one_line_refusal(capsys, generate.main, ["--samples", "20", "--precompression", "0.2", "-q", "--out", str(out)],
                            "precompression 0.2: no start cell reaches it on its isotropic path", out)
    assert not list(tmp_path.iterdir())  # no <out>.parts either


def test_train_and_certify_never_write_over_the_models_own_files(tmp_path, capsys):
    assert_one_line_refusal(capsys, train_command.main, ["--data", str(tmp_path / "db.h5"), "--out", str(tmp_path / "m.json")],
                            "the model's file name ends in .pt", tmp_path / "m.json")
    model = default_model_path(2)
    if model.is_file():
        assert_one_line_refusal(capsys, certify.main, ["--model", str(model), "--out", str(model.with_suffix(".json"))],
                                "is the model's own file", tmp_path / "none")


def test_a_csv_saved_by_a_spreadsheet_with_a_byte_order_mark_is_read(tmp_path):
    """Excel's "CSV UTF-8" starts with a byte-order mark: the data read the same as without it."""
    from homogenization.calibration.data import read_test  # noqa: PLC0415

    text = UNDRAINED + "eps1,q\n0.004,1.1e6\n0.008,1.8e6\n"
    (tmp_path / "plain.csv").write_text(text, encoding="utf-8")
    (tmp_path / "excel.csv").write_text(text, encoding="utf-8-sig")
    plain, excel = read_test(tmp_path / "plain.csv"), read_test(tmp_path / "excel.csv")
    assert (excel.p0, list(excel.eps1), list(excel.observed["q"])) == (plain.p0, list(plain.eps1), list(plain.observed["q"]))


def test_generate_refuses_start_cells_for_a_mesostructure_that_starts_from_itself(tmp_path, capsys):
    out = tmp_path / "db.h5"
    assert_one_line_refusal(capsys, generate.main, ["--mesostructure", "hcell:alpha0=55", "--n-alpha0", "4",
                                                    "--out", str(out)], "--n-alpha0 sets the plain H-cell's", out)
