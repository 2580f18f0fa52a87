"""Every command answers --help without the heavy libraries: its module and parser import
neither torch nor Warp (nor, for the commands of the learning loop, h5py, scipy or matplotlib);
those load inside the command's run (docs/architecture.md). Structural, not timed: each
command is imported in a fresh interpreter and its ``sys.modules`` read."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from homogenization.cli.hmodel import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
NEVER_FOR_HELP = ("torch", "warp")
"""Top-level packages that no command's parser may import."""
LEARNING_COMMANDS = ("train", "certify", "learn")
ALSO_NOT_FOR_LEARNING = ("h5py", "scipy", "matplotlib", "numba")
"""Further packages the parsers of the learning loop's commands (``LEARNING_COMMANDS``) leave unloaded."""
PROBE = """
import importlib, json, sys
entry = importlib.import_module(sys.argv[1])
command = sys.modules[entry.main.__module__]
parser = getattr(command, "build_parser", None)
if parser is not None:
    parser().format_help()
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""


def loaded_by_help(module: str, path: Path = ROOT) -> set[str]:
    """Top-level packages loaded in a fresh interpreter by importing ``module`` (a command's
    ``python -m`` entry, found on ``path`` and the repository) and building its parser and help."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys((str(path), str(ROOT))))}
    done = subprocess.run([sys.executable, "-c", PROBE, module], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=120, check=True)
    return set(json.loads(done.stdout.splitlines()[-1]))


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_command_s_help_imports_neither_torch_nor_warp(command):
    banned = NEVER_FOR_HELP + (ALSO_NOT_FOR_LEARNING if command in LEARNING_COMMANDS else ())
    loaded = loaded_by_help(COMMANDS[command][0]) & set(banned)
    assert not loaded, f"hmodel {command} --help imports {sorted(loaded)}; import them inside the command's run"


def test_the_probe_sees_a_heavy_import(tmp_path):
    (tmp_path / "heavy_command.py").write_text("import torch\n\n\ndef main():\n    return 0\n")
    assert "torch" in loaded_by_help("heavy_command", tmp_path)
