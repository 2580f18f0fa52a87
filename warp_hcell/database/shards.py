"""Storage and resume of the database generator: the sidecar folder ``<out>.parts``.

The sidecar holds the completed work of an unfinished run: ``run.json`` (what identifies the
run, and the provenance of its start), one ``start_XXXXXX.npz`` per explored start cell,
``states.npz`` (the whole exploration), and one ``chunk_XXXXXX.npz`` per chunk of samples, each
compressed (lossless: the sidecar of a large 3D database would otherwise hold its whole raw size).
Every file is written to a temporary name, synced and renamed, so a killed run leaves either
a complete file or none; a file that is unreadable anyway (disk trouble, a foreign file) is
found by ``Sidecar.load`` and the work is redone. A full disk raises ``DiskFull`` after
removing the temporary file.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np


class DiskFull(OSError):
    """No space left while writing ``filename``; nothing partial was left behind."""


def save_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` atomically (temporary name, fsync, rename), compressed.

    Raises:
        DiskFull: no space left on the device (the temporary file is removed).
    """
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, **{name.replace("/", ":"): value for name, value in arrays.items()})
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno == errno.ENOSPC:
            raise DiskFull(errno.ENOSPC, "no space left on device", str(path)) from None
        raise


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """Arrays saved by ``save_npz`` (names restored)."""
    with np.load(path) as data:
        return {name.replace(":", "/"): data[name] for name in data.files}


def sidecar_path(out: Path) -> Path:
    """Folder holding the completed work of an unfinished run writing ``out``."""
    return out.with_name(out.name + ".parts")


class Sidecar:
    """The sidecar of one run (module docstring).

    Args:
        out: the database file the run writes.
    """

    def __init__(self, out: Path):
        self.out = Path(out)
        self.path = sidecar_path(self.out)

    def open(self, description: Mapping[str, Any], provenance: Callable[[], Mapping[str, str]],
             discard_other: bool) -> dict[str, Any]:
        """Start or resume the run described by ``description``; returns its record.

        The record keeps ``provenance()`` of the run's start, so a resumed run writes the
        same attrs as an uninterrupted one.

        Raises:
            ValueError: (one line) the sidecar holds a run with other options and not
                ``discard_other``.
        """
        run_file = self.path / "run.json"
        record = self._read_run(run_file)
        if record is not None and record.get("description") != description:
            if not discard_other:
                raise ValueError(f"{self.path} holds an unfinished run with other options; "
                                 f"rerun it with the same options or pass --overwrite to discard it")
            record = None
        if record is None:
            self.remove()
            self.path.mkdir(parents=True, exist_ok=True)
            record = {"description": description, "provenance": dict(provenance())}
            tmp = run_file.with_name("run.json.tmp")
            try:
                tmp.write_text(json.dumps(record, indent=1, sort_keys=True))
                os.replace(tmp, run_file)
            except OSError as exc:
                tmp.unlink(missing_ok=True)
                if exc.errno == errno.ENOSPC:
                    self.remove()
                    raise DiskFull(errno.ENOSPC, "no space left on device", str(run_file)) from None
                raise
        return json.loads(run_file.read_text())

    @staticmethod
    def _read_run(run_file: Path) -> dict[str, Any] | None:
        try:
            return json.loads(run_file.read_text())
        except (OSError, ValueError):
            return None

    def file(self, kind: str, index: int | None = None) -> Path:
        """Path of ``kind`` (``states``) or of ``kind_XXXXXX`` (``chunk``, ``start``)."""
        return self.path / (f"{kind}.npz" if index is None else f"{kind}_{index:06d}.npz")

    def load(self, path: Path, check: Callable[[Mapping[str, np.ndarray]], bool] | None = None
             ) -> dict[str, np.ndarray] | None:
        """The arrays of ``path``, or None when it is missing or unreadable (then it is removed:
        the work is redone), or when ``check(arrays)`` is False."""
        if not path.exists():
            return None
        try:
            arrays = load_npz(path)
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
            arrays = None
        if arrays is None or (check is not None and not check(arrays)):
            path.unlink(missing_ok=True)
            return None
        return arrays

    def save(self, path: Path, arrays: Mapping[str, np.ndarray]) -> None:
        """``save_npz`` into the sidecar."""
        save_npz(path, arrays)

    def remove(self) -> None:
        """Delete the sidecar folder."""
        shutil.rmtree(self.path, ignore_errors=True)
