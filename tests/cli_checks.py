"""Checks shared by the command-line tests."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import pytest


def assert_usage_error(capsys, cli: Callable[[list[str]], int], argv: Sequence[str], message: str, out: Path) -> None:
    """``cli(argv)`` exits with code 2 through argparse, its last stderr line ends with
    ``error: MESSAGE``, and it leaves nothing at ``out``."""
    with pytest.raises(SystemExit) as info:
        cli(list(argv))
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(f"error: {message}")
    assert not out.exists()
