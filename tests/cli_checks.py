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


def assert_one_line_refusal(capsys, main: Callable[[list[str]], int], argv: Sequence[str], expected: str,
                            out: Path) -> None:
    """``run_main(main, argv)`` exits with code 2, through argparse (a flag's type) or a ``UserError``, printing
    one stderr line that contains ``expected``, and leaves nothing at ``out``."""
    from warp_hcell.core.cli import run_main  # noqa: PLC0415

    try:
        code = run_main(main, list(argv))
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and expected in lines[0], lines
    assert not out.exists()


def replayed_shear(posterior: Path, out: Path):
    """(eps1 (k,), q (k,) [Pa]) of the shear stage of ``hmodel triaxial --posterior POSTERIOR`` at void ratio 0.6,
    drained, p0 = 2e5 Pa to 1.2 % in increments of 4e-3 (Lebedev 11 x 4 aligned), run into ``out``; eps1 counted
    from the shear stage's start."""
    import numpy as np  # noqa: PLC0415

    from homogenization.cli import triaxial  # noqa: PLC0415
    from warp_hcell.core.cli import run_main  # noqa: PLC0415

    assert run_main(triaxial.main, ["--posterior", str(posterior), "--void-ratio", "0.6", "--drained", "--p0", "2e5",
                                    "--eps-max", "0.012", "--increment", "4e-3", "--iso-increment", "2e-3", "--order",
                                    "11", "--spins", "4", "--aligned-spins", "-q", "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "curve.csv", delimiter=",", names=True, dtype=None, encoding=None)
    start = int(np.flatnonzero(rows["stage"] != rows["stage"][0])[0]) - 1
    return rows["eps11"][start + 1:] - rows["eps11"][start], rows["q"][start + 1:]


def interlocking_data(path: Path, test: str = "triaxial_drained") -> Path:
    """A three-point calibration CSV of ``test`` at p0 = 200 kPa and void ratio 0.6 (the interlocking's flag tests),
    written to ``path``."""
    path.write_text(f"# test = {test}\n# p0 = 200000\n# void_ratio = 0.6\neps1,q,eps_v\n0.004,250000,0.001\n"
                    f"0.008,380000,0.0015\n0.012,430000,0.001\n")
    return path


def assert_interlocking_refusal(tmp_path: Path, capsys, flags: Sequence[str], data: str, expected: str,
                                prior: dict, fast: Sequence[str]) -> None:
    """``hmodel calibrate`` on ``interlocking_data`` (its ``# void_ratio`` line dropped where ``data`` is "none"),
    with each "PRIOR" of ``flags`` replaced by a prior file holding ``prior``, then ``fast``: one stderr line naming
    ``expected``, exit 2, no output folder (``assert_one_line_refusal``)."""
    import json  # noqa: PLC0415

    from homogenization.cli import calibrate  # noqa: PLC0415

    prior_file = tmp_path / "prior.json"
    prior_file.write_text(json.dumps(prior))
    flags = [str(prior_file) if f == "PRIOR" else f for f in flags]
    path = interlocking_data(tmp_path / "t.csv")
    if data == "none":
        path.write_text("".join(line for line in path.read_text().splitlines(keepends=True) if "void_ratio" not in line))
    out = tmp_path / "cal"
    args = ["--data", str(path), *flags, "--walkers", "4", "--steps", "2", "--out", str(out), *fast]
    assert_one_line_refusal(capsys, calibrate.main, args, expected, out)


TOY_CALIBRATION = ["--orientations", "4", "--increment", "4e-3", "--iso-increment", "2e-3", "--confirm", "none",
                   "--resolution", "off", "--params", "phi_g,alpha0", "--walkers", "6", "-q"]
"""The flags of a calibration of ``toy_biaxial_data`` that runs in about a second per step (with --start prior or a
--start-point; --steps and --out to add)."""


def toy_biaxial_data(folder: Path) -> list[str]:
    """Two three-point biaxial tests (drained, undrained; p0 2e5 N/m) written into ``folder``; returns their
    --data flags."""
    drained, undrained = folder / "drained.csv", folder / "undrained.csv"
    drained.write_text("# test = drained\n# p0 = 2e5\neps1,q\n0.004,1.2e5\n0.008,1.6e5\n0.012,1.8e5\n")
    undrained.write_text("# test = undrained\n# p0 = 2e5\neps1,q\n0.004,1.0e5\n0.008,1.3e5\n0.012,1.4e5\n")
    return ["--data", str(drained), "--data", str(undrained)]
