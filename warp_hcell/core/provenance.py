"""Provenance stored in every output file: package and library versions, git revision, processor, command.

``package_versions()`` reads the versions of the installed distributions (this package and
its numerical dependencies), ``git_revision()`` the commit of the source tree when it is a
git checkout, ``cpu_model()`` the processor (timings and results off the bit-identical paths
depend on it), and ``provenance()`` combines them with the Python version and the command
line, as flat strings ready for HDF5 or JSON attributes.
"""

from __future__ import annotations

import hashlib
import platform
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path

DISTRIBUTION = "meso-hmodel"
"""Distribution name of this package (pyproject.toml)."""
DISTRIBUTIONS = (DISTRIBUTION, "numpy", "h5py", "warp-lang", "torch")
"""Distributions whose versions are recorded."""


def package_version(distribution: str) -> str:
    """Installed version of ``distribution``, or "not installed"."""
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "not installed"


def package_versions() -> dict[str, str]:
    """Versions of this package and of its numerical dependencies, by distribution name."""
    return {name: package_version(name) for name in DISTRIBUTIONS}


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor as the system names it: the first ``model name`` of ``cpuinfo`` (Linux), else
    ``platform.processor()``, else ``platform.machine()``, else "unknown"."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_revision() -> str:
    """Commit of the source tree this module was loaded from, with "-dirty" appended when a
    tracked file differs from it (untracked files do not count), or "unknown" outside a checkout."""
    here = Path(__file__).resolve().parent
    try:
        result = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10,
                                check=True)
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                 capture_output=True, text=True, timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    revision = result.stdout.strip()
    if not revision:
        return "unknown"
    return revision + "-dirty" if changed.stdout.strip() else revision


def command_line() -> str:
    """The command that started this process, shell-quoted (``python -m MODULE ...`` for -m runs)."""
    if not sys.argv or not sys.argv[0]:
        return ""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    head = ["python", "-m", spec.name] if spec is not None and spec.name != "__main__" else [Path(sys.argv[0]).name]
    return shlex.join([*head, *sys.argv[1:]])


def file_sha256(path: Path) -> str:
    """SHA-256 hex digest of the file ``path`` (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def provenance(command: str | None = None) -> dict[str, str]:
    """Code version, git revision, Python and library versions, the processor (``cpu_model``), and the
    command line (``command``, or this process's own when None)."""
    versions = package_versions()
    return {
        "code_version": versions["meso-hmodel"],
        "git_revision": git_revision(),
        "python_version": platform.python_version(),
        "numpy_version": versions["numpy"],
        "h5py_version": versions["h5py"],
        "warp_version": versions["warp-lang"],
        "torch_version": versions["torch"],
        "cpu": cpu_model(),
        "command": command_line() if command is None else command,
    }
