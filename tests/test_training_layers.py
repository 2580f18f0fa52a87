"""The training package is a library with two command modules: only ``training.train`` (``python -m
training.train``) and ``training.ood_command`` (``python -m training.ood``) import the command helpers
``warp_hcell.core.cli`` (argparse, progress bars, status lines); the library takes a progress
callback and a log callback instead."""

import pytest

from test_architecture import _imports, _name, MODULES

COMMAND_MODULES = ("training.train", "training.ood_command")
"""The commands of ``training`` (``training.ood`` runs ``training.ood_command`` as its ``__main__``)."""


def _imports_the_command_helpers(path) -> bool:
    return any(name == "warp_hcell.core.cli" or name.startswith("warp_hcell.core.cli.") for _, name in _imports(path))


@pytest.mark.parametrize("path", [p for p in MODULES
                                  if _name(p).startswith("training.") and _name(p) not in COMMAND_MODULES],
                         ids=lambda p: _name(p))
def test_library_modules_of_training_do_not_import_the_command_helpers(path):
    assert not _imports_the_command_helpers(path), f"{_name(path)} is a library module and imports warp_hcell.core.cli"


def test_the_command_modules_of_training_are_python_m_entries():
    for module in COMMAND_MODULES:
        path = next(p for p in MODULES if _name(p) == module)
        assert _imports_the_command_helpers(path) and "__main__" in path.read_text(), module
        assert "import torch" not in path.read_text(), module  # light: their parsers build at once


def test_the_training_command_builds_its_help_without_torch():
    from test_cli_help_imports import loaded_by_help

    assert not loaded_by_help("training.train") & {"torch", "warp", "h5py"}


def test_python_m_training_ood_is_still_the_index_command(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "training.ood", "--model", str(tmp_path / "none.pt"), "--data",
                           str(tmp_path / "none.h5")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "--model" in subprocess.run([sys.executable, "-m", "training.ood", "--help"], capture_output=True,
                                       text=True, timeout=120).stdout
