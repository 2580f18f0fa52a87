"""``pip install`` through uv: what pip would install here, several times faster from a cold cache.

uv reads no pip configuration, so this passes it pip's own, as ``pip config list`` gives it (the
environment's ``PIP_*`` variables over the ``[install]`` section over ``[global]``): index URL, extra
index URLs, find-links, constraints, no-index, certificate bundle and timeout; and pip's choice among
indexes, the newest version on any (``unsafe-best-match``). Unlike pip, uv compiles no bytecode at
install: Python does it on first import, for the modules imported (unless PYTHONDONTWRITEBYTECODE is
set). Installs into this interpreter's environment.

    .venv/bin/python .ci/uv_pip_install.py [pip install arguments, e.g. torch==2.13.0, -e '.[dev]']

Installs uv (MIT or Apache-2.0) with pip into the same environment if it is not there. Exit status: uv's.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

RANK = {"global": 0, "install": 1, ":env:": 2}
"""pip's precedence of a configuration section: a higher rank wins."""
LISTS = {"extra-index-url": "--extra-index-url", "find-links": "--find-links", "constraint": "--constraint"}
"""pip's list options (values split on white space) and uv's flag for each value."""


def pip_options() -> dict[str, str]:
    """pip's configured options for ``pip install``: {option name: value as written}."""
    listing = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True,
                             check=True).stdout
    best: dict[str, tuple[int, str]] = {}
    for line in listing.splitlines():
        key, _, value = line.partition("=")
        section, _, option = key.rpartition(".")
        rank = RANK.get(section)
        if rank is not None and rank >= best.get(option, (-1, ""))[0]:
            best[option] = (rank, ast.literal_eval(value))
    return {option: value for option, (_, value) in best.items()}


def uv_command(options: dict[str, str], argv: list[str]) -> list[str]:
    """The ``uv pip install`` command line that installs ``argv`` as pip would with ``options``."""
    uv = Path(sys.executable).with_name("uv")
    command = [str(uv), "pip", "install", "--python", sys.executable, "--index-strategy", "unsafe-best-match"]
    if options.get("index-url"):
        command += ["--index-url", options["index-url"]]
    for option, flag in LISTS.items():
        for value in options.get(option, "").split():
            command += [flag, value]
    if options.get("no-index", "").lower() in ("1", "true", "yes", "on"):
        command.append("--no-index")
    return command + argv


def main(argv: list[str]) -> int:
    if not Path(sys.executable).with_name("uv").exists():  # an environment made before the Makefile used uv
        subprocess.run([sys.executable, "-m", "pip", "install", "uv"], check=True)
    options = pip_options()
    env = dict(os.environ)
    if options.get("cert"):
        env.setdefault("SSL_CERT_FILE", options["cert"])
    timeout = options.get("timeout") or options.get("default-timeout")
    if timeout:
        env.setdefault("UV_HTTP_TIMEOUT", timeout)
    return subprocess.run(uv_command(options, argv), env=env).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
