"""The ``hmodel`` console script: --version, dispatch to every subcommand, the declared entry point."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from homogenization.cli import hmodel

ROOT = Path(__file__).resolve().parents[1]


def test_version_is_the_installed_distribution(capsys):
    assert hmodel.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"hmodel {metadata.version('meso-hmodel')}"


def test_pyproject_declares_the_console_script():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    module, function = project["scripts"]["hmodel"].split(":")
    assert (module, function) == (hmodel.__name__, "main")


@pytest.mark.parametrize("command", sorted(hmodel.COMMANDS))
def test_every_subcommand_has_help(command, capsys):
    assert hmodel.main([command, "--help"]) == 0
    assert "--" in capsys.readouterr().out  # the subcommand's own options were listed


def test_biaxial_help_lists_its_options(capsys):
    assert hmodel.main(["biaxial", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--programme" in out and "--alpha0" in out and "--kn" in out


def test_unknown_command_and_bad_option_exit_2(capsys):
    assert hmodel.main(["nonsense"]) == 2
    assert hmodel.main(["biaxial", "--alpha0", "20", "--out", "x"]) == 2
    assert "alpha0" in capsys.readouterr().err


def test_user_error_of_a_subcommand_is_one_line(tmp_path, capsys):
    assert hmodel.main(["plot", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "f.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hmodel plot: error:") and "missing.h5" in err


def test_module_form_runs_the_same_entry_point():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "homogenization.hmodel", "--version"], capture_output=True,
                          text=True, env=env, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == f"hmodel {metadata.version('meso-hmodel')}"
    assert "warp" not in done.stderr.lower()


def test_exit_codes_of_subcommand_system_exits():
    assert hmodel.exit_code(SystemExit()) == 0
    assert hmodel.exit_code(SystemExit(3)) == 3
    assert hmodel.exit_code(SystemExit("message")) == 2


def test_ctrl_c_while_a_command_loads_is_one_line(monkeypatch, capsys):
    """Ctrl-C before the command's own handler is in place (its modules still loading): one line, exit 130."""
    def interrupted(name):
        raise KeyboardInterrupt

    monkeypatch.setattr(hmodel.importlib, "import_module", interrupted)
    assert hmodel.main(["calibrate", "--help"]) == 130
    err = capsys.readouterr().err
    assert err == "hmodel calibrate: interrupted\n"
