"""Output files and folders that a failed or concurrent run never leaves half written.

- ``check_output_path(path, overwrite=...)``: refuse existing output, check the folder is
  writable, before any work;
- ``atomic_write(path)``: a temporary file renamed onto ``path`` on success;
- ``output_lock(path)``: an exclusive lock, so that a second run on the same output exits at
  once (``UserError``); SIGTERM runs the same clean-up as Ctrl-C inside it; taking it removes
  the temporary files that a killed run's ``atomic_write`` left (``remove_stale_temporaries``);
- ``output_folder(path)``: a hidden working folder that replaces ``path`` as a unit.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from warp_hcell.core.errors import UserError


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


TEMPORARY_SUFFIX = ".tmp"
"""Suffix of the temporary files of ``atomic_write``."""
_TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.[a-z0-9_]{8}" + re.escape(TEMPORARY_SUFFIX))
"""Name of a temporary file of ``atomic_write``: ``.NAME.`` then mkstemp's eight characters."""


def temporary_of(candidate: Path) -> str | None:
    """The file name NAME whose ``atomic_write`` temporary ``candidate`` is, or None if it is not one."""
    match = _TEMPORARY_NAME.fullmatch(Path(candidate).name)
    return None if match is None else match.group("name")


@contextmanager
def atomic_write(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    An interrupted or failed run therefore never leaves a truncated file in place of a good
    one. The file gets the usual permissions (0666 less the umask), not mkstemp's 0600. Its
    name is ``.NAME.XXXXXXXX.tmp`` (eight random characters, so that concurrent writers never
    share one); the one a SIGKILL leaves behind is removed by the next run that takes
    ``output_lock`` on ``path`` or on its folder (``remove_stale_temporaries``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX, dir=path.parent)
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


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove what a killed ``atomic_write`` left of output ``path``: its temporaries next to it
    and, for a folder, those of the files in it. Call only while holding ``output_lock(path)``
    (every writer of ``path`` holds it, so no live run owns them). Returns the files removed."""
    path = Path(path)
    stale = [p for p in path.parent.iterdir() if temporary_of(p) == path.name]
    if path.is_dir():
        stale += [p for p in path.iterdir() if temporary_of(p) is not None]
    stale = [p for p in stale if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def _sibling(path: Path, tag: str) -> Path:
    """Hidden working name next to ``path``: ``.NAME.TAG``."""
    return path.parent / f".{path.name}.{tag}"


REDELIVER_S = 0.5
"""Seconds after which ``sigterm_as_interrupt`` sends an interrupting signal again while its KeyboardInterrupt has
not left the body: Python ignores one raised inside a weakref callback or ``__del__`` (Warp's arrays have them), so
a ``kill`` of a DEM run could be lost and the run go on."""
_INTERRUPTING = threading.Event()


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM (and SIGINT) into KeyboardInterrupt for the body (main thread only), so that ``kill``
    runs the same clean-up as Ctrl-C, the signal sent again every ``REDELIVER_S`` until the interrupt has left
    the body (a lost one is not printed); the previous handlers are restored afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGTERM, signal.SIGINT)}
    hook = sys.unraisablehook

    def quiet(unraisable: Any) -> None:  # a lost interrupt is sent again: no traceback of it on stderr
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            hook(unraisable)
    sys.unraisablehook = quiet
    try:
        yield
    finally:
        _INTERRUPTING.clear()
        sys.unraisablehook = hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def output_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on output ``path`` (file or folder) for the body.

    The lock is ``flock`` on the hidden file ``.NAME.lock`` next to ``path``; a second run
    on the same output raises ``UserError`` (one line) at once instead of waiting. The lock
    file is removed on release, also on Ctrl-C or SIGTERM (``sigterm_as_interrupt``); one
    left by SIGKILL holds no lock (the kernel released it) and is taken over and removed by
    the next run, together with the temporary files of that run's interrupted atomic writes
    to ``path`` (``remove_stale_temporaries``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = _sibling(path, "lock")
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise UserError(f"{path} is being written by another run (lock {lock}); wait for it to finish") from None
            raise
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the previous holder removed the file while we opened it: take the new one
    try:
        remove_stale_temporaries(path)
        with sigterm_as_interrupt():
            yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths (Linux ``renameat2(RENAME_EXCHANGE)``); False if unsupported."""
    libc = ctypes.CDLL(None, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    if ctypes.get_errno() in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()), str(b))


@contextmanager
def output_folder(path: Path) -> Iterator[Path]:
    """Yield an empty hidden folder next to ``path``; on success it replaces ``path`` as a unit.

    Everything written into the yielded folder appears at ``path`` at once (an atomic
    directory exchange where the file system has one, else two renames), so a reader never
    sees files of two runs mixed. On failure or interruption the folder is removed and
    ``path`` is untouched. Use inside ``output_lock(path)``, which also turns SIGTERM into
    KeyboardInterrupt: a working folder left by SIGKILL is removed when the next run starts.
    """
    path = Path(path)
    work = _sibling(path, "partial")
    old = _sibling(path, "replaced")
    if old.exists() and not path.exists():
        os.rename(old, path)  # a run killed between the two renames of the fallback: restore
    for stale in (work, old):
        if stale.exists():
            shutil.rmtree(stale)
    work.mkdir(parents=True)
    try:
        yield work
        if not path.exists():
            os.rename(work, path)
        elif _exchange(work, path):
            shutil.rmtree(work)  # now holds the previous output
        else:
            os.rename(path, old)
            os.rename(work, path)
            shutil.rmtree(old)
    finally:
        if work.exists():
            shutil.rmtree(work)


def _raise_interrupt(signum, frame) -> None:
    _INTERRUPTING.set()
    timer = threading.Timer(REDELIVER_S, _redeliver, (signum,))
    timer.daemon = True
    timer.start()
    raise KeyboardInterrupt


def _redeliver(signum: int) -> None:
    """The interrupting signal again, where its KeyboardInterrupt was lost (``REDELIVER_S``)."""
    if _INTERRUPTING.is_set():
        os.kill(os.getpid(), signum)


def stored_settings_differ(path: Path, fmt: str, attribute: str, settings: str) -> list[str]:
    """The dotted names of the settings (JSON text ``settings``) that differ from those stored as JSON in the
    attribute ``attribute`` of the HDF5 file ``path`` (a checkpoint); [] where equal.

    Raises:
        UserError: (one line) the file cannot be read, or its ``format`` attribute is not ``fmt``.
    """
    import h5py  # noqa: PLC0415 (the file helpers above need no HDF5)

    try:
        with h5py.File(path, "r") as f:
            found, stored = f.attrs.get("format"), f.attrs.get(attribute)
    except OSError as exc:
        raise UserError(f"cannot read checkpoint {path}: {exc}") from None
    if found != fmt:
        raise UserError(f"{path} is no {fmt} file (format {found!r})")
    return [] if stored == settings else _differences(json.loads(stored), json.loads(settings))


def _differences(old: Any, new: Any, where: str = "") -> list[str]:
    """The dotted names of the entries that differ between two JSON values (mappings compared entry by entry)."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [name for k in sorted(set(old) | set(new), key=str)
                for name in _differences(old.get(k), new.get(k), f"{where}.{k}" if where else str(k))]
    return [] if old == new else [where or "settings"]
