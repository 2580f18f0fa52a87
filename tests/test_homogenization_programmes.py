"""Programme files (--programme): the shipped examples run, the cyclic one shows three cycles, bad files exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from homogenization.cli import biaxial
from homogenization.element_test import programme as programmes
from homogenization.output import io
from warp_hcell.core.cli import run_main
from warp_hcell.core.parameters import LoadingDefaults

PROGRAMMES = Path(biaxial.__file__).resolve().parents[1] / "data" / "programmes"
FAST = ["--alpha0", "55", "--orientations", "24", "-q"]


def cli(argv: list[str]) -> int:
    return run_main(biaxial.main, argv)


def test_shipped_programmes_are_valid_and_documented():
    files = sorted(PROGRAMMES.iterdir())
    assert {f.suffix for f in files} == {".json", ".toml"}
    docs = (Path(biaxial.__file__).resolve().parents[2] / "docs" / "programmes.md").read_text()
    for path in files:
        programme = programmes.read_programme(path)
        assert programme[0].stop_at_p == 5.85e6
        assert programmes.from_dict(programmes.to_dict(programme)) == programme
        assert path.name in docs


def test_cyclic_programme_runs_three_strain_cycles_at_constant_volume(tmp_path):
    out = tmp_path / "cyclic"
    assert cli(FAST + ["--programme", str(PROGRAMMES / "cyclic_constant_volume.toml"), "--out", str(out)]) == 0
    stored = io.read_run(out / "run.h5")
    record = stored.record
    shear = record.stage != "iso"
    eps1 = record.eps11[shear] - record.eps11[~shear][-1]
    eps_v = record.eps11[shear] + record.eps22[shear] - (record.eps11[~shear][-1] + record.eps22[~shear][-1])
    assert np.abs(eps_v).max() < 1e-12  # constant volume throughout
    reversals = np.flatnonzero(np.diff(np.sign(np.diff(eps1))) != 0) + 1
    assert eps1[reversals] == pytest.approx([0.05, -0.05] * 3, abs=1e-9)  # 3 cycles: +5 %, -5 % each
    assert eps1[-1] == pytest.approx(0.0, abs=1e-9)
    q = record.q[shear]
    assert np.all(q[reversals[::2]] > 0.4 * 5.85e6) and np.all(q[reversals[1::2]] < -0.4 * 5.85e6)
    # hysteresis: at eps1 = 0 the deviator differs between the unloading and reloading branches
    crossings = np.flatnonzero(np.abs(eps1) < 1e-9)[1:]
    assert crossings.size >= 5 and np.ptp(q[crossings]) > 0.5 * 5.85e6
    assert stored.attrs["parameters"]["programme_file"].endswith("cyclic_constant_volume.toml")
    assert stored.attrs["parameters"]["drained"] is False
    assert [s["label"] for s in stored.attrs["programme"]["steps"]][:4] == ["iso", "load_1", "unload_1", "reload_1"]


def test_stress_steps_reach_their_stress_targets(tmp_path):
    out = tmp_path / "stress"
    assert cli(FAST + ["--programme", str(PROGRAMMES / "stress_steps.toml"), "--out", str(out)]) == 0
    record = io.read_run(out / "run.h5").record
    for label, (s11, s22) in {"ramp": (7.5e6, 5.85e6), "unload": (5.85e6, 5.85e6)}.items():
        last = np.flatnonzero(record.stage == label)[-1]
        assert (record.sigma11[last], record.sigma22[last]) == pytest.approx((s11, s22), rel=LoadingDefaults.stress_rtol)
    drained = record.stage == "drained"
    # the drained stage moves sigma22 from where "unload" left it (within the tolerance) to its target
    assert np.abs(record.sigma22[drained] / 5.85e6 - 1).max() <= 2.0 * LoadingDefaults.stress_rtol


def test_proportional_strain_path_follows_its_direction(tmp_path):
    out = tmp_path / "prop"
    assert cli(FAST + ["--programme", str(PROGRAMMES / "proportional_strain.json"), "--out", str(out)]) == 0
    record = io.read_run(out / "run.h5").record
    path = record.stage == "path"
    start = np.flatnonzero(~path)[-1]
    d11, d22 = record.eps11[path] - record.eps11[start], record.eps22[path] - record.eps22[start]
    assert d11[-1] == pytest.approx(0.1) and d22[-1] == pytest.approx(-0.05)
    assert np.allclose(d22, -0.5 * d11)


@pytest.mark.parametrize("content, suffix, message", [
    ("{not json", ".json", "cannot read programme"),
    ('steps = "x"', ".toml", "needs a list of steps"),
    (json.dumps({"steps": [{"control": ["strain", "oops"], "target": [0, 0], "n_increments": 1, "label": "a"}]}),
     ".json", "control must be two of"),
    (json.dumps({"steps": [{"control": ["strain", "strain"], "target": [0.1, 0], "n_increments": 1, "label": "a",
                            "colour": 3}]}), ".json", "unknown key 'colour' in step 1 of"),
    ("{}", ".yaml", "a programme file ends in .json or .toml"),
])
def test_bad_programme_file_one_line_exit_2(tmp_path, capsys, content, suffix, message):
    path = tmp_path / f"p{suffix}"
    path.write_text(content)
    assert cli(["--programme", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and str(path) in err
    assert not (tmp_path / "o").exists()


def test_programme_flags_conflict_with_programme_file(tmp_path, capsys):
    path = PROGRAMMES / "proportional_strain.json"
    assert cli(["--programme", str(path), "--p0", "2e5", "--increment", "1e-4", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip() == ("hmodel: error: --p0, --increment do not apply with --programme "
                                                "(the file holds the whole programme)")
