"""The training package is a library with one command module: only ``training.train`` (``python -m
training.train``) imports the command helpers ``warp_hcell.core.cli`` (argparse, progress bars,
status lines); the library takes a progress callback and a log callback instead."""

import pytest

from test_architecture import _imports, _name, MODULES

COMMAND_MODULES = ("training.train",)
"""The ``python -m`` entries of ``training``."""
NOT_YET = ("training.ood",)
"""Library modules that still hold a command (``python -m training.ood``'s ``main``)."""


def _imports_the_command_helpers(path) -> bool:
    return any(name == "warp_hcell.core.cli" or name.startswith("warp_hcell.core.cli.") for _, name in _imports(path))


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.xfail(strict=True, reason="holds a command"))
                                  if _name(p) in NOT_YET else p for p in MODULES
                                  if _name(p).startswith("training.") and _name(p) not in COMMAND_MODULES],
                         ids=lambda p: _name(p))
def test_library_modules_of_training_do_not_import_the_command_helpers(path):
    assert not _imports_the_command_helpers(path), f"{_name(path)} is a library module and imports warp_hcell.core.cli"


def test_the_command_module_of_training_is_the_python_m_entry():
    path = next(p for p in MODULES if _name(p) == "training.train")
    assert _imports_the_command_helpers(path) and "__main__" in path.read_text()
    assert "import torch" not in path.read_text()  # light: hmodel train builds its parser from it at once


def test_the_training_command_builds_its_help_without_torch():
    from test_cli_help_imports import loaded_by_help

    assert not loaded_by_help("training.train") & {"torch", "warp", "h5py"}
