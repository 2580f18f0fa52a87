"""Bad command lines of every entry point: one line on stderr that names the flag and the fix,
exit code 2, no usage block; --help stays the full help; the program name is the command typed."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from homogenization.cli import hmodel
from warp_hcell.core import cli

ROOT = Path(__file__).resolve().parents[1]
HMODEL = Path(sys.executable).with_name("hmodel")

BAD_VALUES = {
    "biaxial": (["--orientations", "0", "--out", "o"], "argument --orientations: 0 must be >= 1"),
    "cell": (["--alpha0", "20", "--path", "p.csv", "--out", "o.csv"], "argument --alpha0: alpha0 = 20 deg is outside"),
    "plot": (["run.h5", "--deviator", "s", "--out", "f.png"], "argument --deviator: invalid choice: 's'"),
    "generate": (["--samples", "0", "--out", "db.h5"], "argument --samples: 0 must be >= 1"),
    "clean": (["db.h5", "--out"], "argument --out: expected one argument; give it a value: --out OUT"),
    "train": (["--data", "db.h5", "--epochs", "0", "--out", "m.pt"], "argument --epochs: 0 must be > 0"),
    "sweep": (["--p0", "2e5,-1", "--out", "o"], "argument --p0:"),
    "bvp": (["--elements", "3", "--out", "o"], "argument --elements: '3' is not NX,NY"),
    "triaxial": (["--order", "4", "--out", "o"], "argument --order: Lebedev order 4 is not one of"),
    "calibrate": (["--data", "a.csv", "--params", "phi_g,mu", "--out", "o"], "argument --params: unknown parameter 'mu'"),
    "certify": (["--model", "m.pt", "--orientations", "0", "--out", "c.json"], "argument --orientations: 0 must be >= 1"),
    "learn": (["--mesostructure", "hcell", "--samples", "0", "--out", "d"], "argument --samples: 0 must be >= 1"),
}
"""Subcommand -> (argv with one malformed value, the start of the message that names its flag)."""


def module_of(command: str):
    return importlib.import_module(hmodel.COMMANDS[command][0])


def run_module(command: str, argv: list[str]) -> int:
    """``python -m MODULE argv`` in this process: the exit code (SystemExit of argparse included)."""
    try:
        return cli.run_main(module_of(command).main, argv)
    except SystemExit as exc:
        return hmodel.exit_code(exc)


@pytest.mark.parametrize("form", ["hmodel", "python -m"])
@pytest.mark.parametrize("kind", ["option", "value"])
@pytest.mark.parametrize("command", list(hmodel.COMMANDS))
def test_a_bad_command_line_is_one_line_naming_the_flag_and_the_fix(command, kind, form, capsys):
    if kind == "option":  # a misspelt --out: the nearest option is offered
        argv, expected = ["--outt", "x"], "; did you mean --out?"
    else:
        argv, expected = BAD_VALUES[command]
    prog = f"hmodel {command}" if form == "hmodel" else f"python -m {hmodel.COMMANDS[command][0]}"
    code = hmodel.main([command, *argv]) if form == "hmodel" else run_module(command, argv)
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code == 2 and len(lines) == 1 and captured.out == "", captured.err
    assert lines[0].startswith(f"{prog}: error: ") and expected in lines[0]
    if kind == "option":
        assert lines[0].startswith(f"{prog}: error: unrecognized arguments: --outt")


@pytest.mark.parametrize("argv, expected", [
    ([], "the following arguments are required: --out; add --out OUT"),
    (["-q", "-v", "--out", "o"], "argument -v/--verbose: not allowed with argument -q/--quiet; give only one of them"),
    (["--seed", "x", "--out", "o"], "argument --seed: 'x' is not an integer"),
    (["--seed", "99999999999999999999999", "--out", "o"], "argument --seed: 99999999999999999999999 must be below 2**63"),
    (["--seed", "-1", "--out", "o"], "argument --seed: -1 must be >= 0"),
    (["--o", "x"], "unrecognized arguments: --o x"),  # no abbreviations: --mod is not --model-error
    (["--outp", "x"], "unrecognized arguments: --outp x"),
    (["--bogus", "1"], "unrecognized arguments: --bogus 1; see 'hmodel biaxial --help'"),
    (["--mesostructure", "nope", "--out", "o"], "argument --mesostructure: mesostructure 'nope' is neither a file"),
])
def test_every_kind_of_argparse_error_is_one_line(argv, expected, capsys):
    assert hmodel.main(["biaxial", *argv]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hmodel biaxial: error: ") and expected in lines[0], lines


def test_an_unknown_option_is_named_before_missing_required_ones(capsys):
    assert hmodel.main(["train", "--epoch", "3", "--hiden", "8"]) == 2
    assert capsys.readouterr().err == ("hmodel train: error: unrecognized arguments: --hiden 8; "
                                       "did you mean --hidden?\n")


def test_hmodel_without_a_command(capsys):
    assert hmodel.main([]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hmodel: error: give a COMMAND, one of: biaxial, cell")


@pytest.mark.parametrize("command", list(hmodel.COMMANDS))
def test_help_and_usage_name_the_command_typed(command, capsys):
    module = hmodel.COMMANDS[command][0]
    assert hmodel.main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: hmodel {command} ") and "-v, --verbose" in out and "options:" in out
    assert run_module(command, ["--help"]) == 0
    assert capsys.readouterr().out.startswith(f"usage: python -m {module} ")


def test_real_processes_name_the_command_and_print_no_usage_block(tmp_path):
    """The console script and python -m, as typed in a shell (help: test_help_and_usage_name_the_command_typed)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for head, prog in (([str(HMODEL), "train"], "hmodel train"),
                       ([sys.executable, "-m", "training.train"], "python -m training.train")):
        bad = subprocess.run([*head, "--data", "db.h5", "--out", str(tmp_path / "m.pt"), "--lr", "fast"],
                             capture_output=True, text=True, env=env, timeout=120)
        assert bad.returncode == 2 and bad.stdout == ""
        assert bad.stderr == f"{prog}: error: argument --lr: 'fast' is not a float\n"
