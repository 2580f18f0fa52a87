"""Shared command-line plumbing: the parent parser, argument validators, user errors.

Every entry point builds its parser with ``parents=[common_parser()]`` and
``formatter_class=argparse.ArgumentDefaultsHelpFormatter``, validates values with the
``type=`` functions below (a bad value is one line on stderr and exit code 2), and runs its
body through ``run_main`` so that a ``UserError`` or ``ValueError`` (bad files, inconsistent
options) is also one line and exit code 2, never a traceback. Set ``HMODEL_DEBUG=1`` to get
the traceback anyway.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Sequence

from warp_hcell.parameters import check_alpha0_deg

EXIT_USAGE = 2
"""Exit code for bad user input (argparse's own convention)."""


class UserError(Exception):
    """Bad input that the user can fix; reported as one line with exit code 2."""


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not finite")
    return value


def finite_float(text: str) -> float:
    """argparse type: a finite float."""
    return _float(text)


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0."""
    value = _float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"{text} must be > 0")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be >= 1")
    return value


def alpha0_deg(text: str) -> float:
    """argparse type: initial opening angle [deg] in [30, 90)."""
    try:
        return check_alpha0_deg(_float(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def common_parser() -> argparse.ArgumentParser:
    """Parent parser with the flags every entry point shares: --device, --seed, --overwrite."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--device", default="cpu", help="compute device: cpu, or cuda / cuda:N where Warp/torch see a GPU")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice (runs are bit-reproducible)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output instead of refusing")
    return parser


def check_output_path(path: Path, *, overwrite: bool) -> Path:
    """Refuse to overwrite an existing file or a non-empty folder unless ``overwrite``.

    Also checks that the nearest existing parent folder is writable, so a run fails before
    computing rather than after. Returns ``path``.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        if path.is_file() or (path.is_dir() and any(path.iterdir())):
            raise UserError(f"{path} exists; pass --overwrite to replace it")
    parent = path if path.is_dir() else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"cannot write to {path}: {parent} is not a folder")
    if not os.access(parent, os.W_OK):
        raise UserError(f"cannot write to {parent}")
    return path


@contextmanager
def atomic_write(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    An interrupted or failed run therefore never leaves a truncated file in place of a good
    one. The file gets the usual permissions (0666 less the umask), not mkstemp's 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def run_main(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Run ``main(argv)``; map user errors to one line on stderr and exit code 2."""
    prog = Path(sys.argv[0]).name if argv is None else "hmodel"
    try:
        return int(main(argv) or 0)
    except (UserError, ValueError, FileNotFoundError) as exc:
        if os.environ.get("HMODEL_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"{prog}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
