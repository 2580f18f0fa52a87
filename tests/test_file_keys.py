"""A key that nothing reads in a mesostructure or programme file is refused with its name: one
line, exit code 2, before any run, the existing output untouched (a misspelt ``pairs`` or a
per-grain ``friction`` was silently ignored)."""

from __future__ import annotations

import json
import time
import tomllib
from pathlib import Path

import pytest

from homogenization.element_test import programme as programmes
from homogenization.cli import biaxial, triaxial
from warp_hcell.core import cli
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.mesostructure import MesostructureError

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "warp_hcell" / "data" / "h_cell_fine_grain.toml"
PROGRAMMES = ROOT / "homogenization" / "data" / "programmes"
TINY = ["--alpha0", "55", "--eps-max", "0.002", "--increment", "5e-4", "--orientations", "12", "-q"]


def edited(tmp_path: Path, source: Path, old: str, new: str, name: str) -> Path:
    text = source.read_text()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


MESO_CASES = {
    "pair": ('type1 = [[1, 2]', 'pair = [[1, 2], [2, 3]]\ntype1 = [[1, 2]',
             "unknown key 'pair' at the top level of {path} (did you mean 'pairs'?); expected one of: name, cell_size, "
             "outer, pairs, type1, type2, grains"),
    "typ1": ("type1 =", "typ1 =", "unknown key 'typ1' at the top level of {path} (did you mean 'type1'?)"),
    "friction": ("radius = 0.5\nposition = [-0.5,", "radius = 0.5\nfriction = 0.3\nposition = [-0.5,",
                 "unknown key 'friction' in grain 3 of {path}; expected one of: radius, position, driven"),
}


@pytest.mark.parametrize("case", list(MESO_CASES))
def test_an_unknown_key_of_a_mesostructure_file_is_named(case, tmp_path):
    old, new, message = MESO_CASES[case]
    path = edited(tmp_path, CELL, old, new, f"{case}.toml")
    with pytest.raises(MesostructureError) as info:
        load_mesostructure(path)
    assert message.format(path=path) in str(info.value)
    as_json = tmp_path / f"{case}.json"  # the same in JSON
    as_json.write_text(json.dumps(tomllib.loads(path.read_text())))
    with pytest.raises(MesostructureError, match=f"unknown key '{case}'"):
        load_mesostructure(as_json)


def test_the_shipped_files_have_no_unknown_key():
    for path in sorted((ROOT / "warp_hcell" / "data").glob("*.toml")):
        load_mesostructure(path)
    for path in sorted(PROGRAMMES.iterdir()):
        programmes.read_programme(path)


@pytest.fixture
def previous_run(tmp_path) -> Path:
    out = tmp_path / "run"
    assert cli.run_main(biaxial.main, TINY + ["--out", str(out)]) == 0
    return out


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    return lines[0]


def test_biaxial_refuses_a_mesostructure_file_with_an_unknown_key_before_any_run(previous_run, tmp_path, capsys):
    path = edited(tmp_path, CELL, "type1 =", "typ1 =", "typ1.toml")
    before = snapshot(tmp_path)
    start = time.perf_counter()
    code = cli.run_main(biaxial.main, ["--backend", "dem", "--mesostructure", str(path), *TINY, "--overwrite",
                                       "--out", str(previous_run)])
    assert code == 2 and time.perf_counter() - start < 10.0
    assert one_error_line(capsys).startswith(f"hmodel: error: unknown key 'typ1' at the top level of {path}")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("source, old, new, message", [
    ("cyclic_constant_volume.toml", "stop_at_p =", "stop_at =",
     "unknown key 'stop_at' in step 1 of {path} (did you mean 'stop_at_p'?); expected one of: control, target, "
     "n_increments, label, stop_at_p, coupling"),
    ("proportional_strain.json", '"steps": [', '"step": 1, "steps": [',
     "unknown key 'step' at the top level of {path} (did you mean 'steps'?); expected one of: steps"),
    ("stress_steps.toml", "n_increments =", "n_increment =", "unknown key 'n_increment' in step 1 of {path}"),
])
def test_an_unknown_key_of_a_programme_file_is_named(source, old, new, message, previous_run, tmp_path, capsys):
    path = edited(tmp_path, PROGRAMMES / source, old, new, "bad" + Path(source).suffix)
    with pytest.raises(programmes.UnknownKey) as info:
        programmes.read_programme(path)
    assert message.format(path=path) in str(info.value)
    before = snapshot(tmp_path)
    code = cli.run_main(biaxial.main, ["--programme", str(path), "--orientations", "12", "-q", "--overwrite",
                                       "--out", str(previous_run)])
    assert code == 2 and one_error_line(capsys).startswith("hmodel: error: " + message.format(path=path))
    assert snapshot(tmp_path) == before


def test_triaxial_names_an_unknown_key_of_its_programme(tmp_path, capsys):
    steps = {"steps": [{"label": "iso", "control": ["strain"] * 3, "target": [0.01] * 3, "n_increments": 10,
                        "stop_at_p": 2e5, "couplng": [0, 0, 0]}]}
    path = tmp_path / "tri.json"
    path.write_text(json.dumps(steps))
    assert cli.run_main(triaxial.main, ["--programme", str(path), "-q", "--out", str(tmp_path / "out")]) == 2
    assert one_error_line(capsys).startswith(f"hmodel: error: unknown key 'couplng' in step 1 of {path} "
                                             f"(did you mean 'coupling'?)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tri.json"]


def test_a_stored_programme_keeps_reading_back():
    programme = programmes.triaxial(2e5, 0.01, 1e-3, test="true", iso_increment=5e-4, b=0.5)
    assert programmes.from_dict(programmes.to_dict(programme)) == programme
    with pytest.raises(programmes.UnknownKey, match="unknown key 'extra' in step 2;"):
        programmes.from_dict({"steps": [*programmes.to_dict(programme)["steps"][:1],
                                     {**programmes.to_dict(programme)["steps"][1], "extra": 1}]})


SPATIAL_CELL = ROOT / "benchmarks" / "cells" / "fine_off_centre.toml"
INVALID_CELLS = {  # (file, old text, new text, the message): each loaded before, with a wrong volume or silently
    "polygon crossing itself": (CELL, "outer = [1, 2, 3, 4, 5, 6]", "outer = [1, 3, 2, 4, 6, 5]",
                                "the outer polygon's edges 1-3 and 2-4 cross"),  # area 0.940 instead of 2.087
    "nested outer": (CELL, "outer = [1, 2, 3, 4, 5, 6]", "outer = [[1, 2, 3], [4, 5, 6]]", "is not a grain label"),
    "fractional label": (CELL, "outer = [1, 2, 3, 4, 5, 6]", "outer = [1.5, 2, 3, 4, 5, 6]", "1.5 is not a grain label"),
    "labelled twice": (CELL, "type2 = [[2, 3], [5, 6]]", "type2 = [[2, 3], [5, 6], [1, 2]]",
                       "pair 1-2 is labelled both type 1 and type 2"),
    "fine grain outside": (CELL, "position = [0.0, 0.0]", "position = [5.0, 5.0]",
                           "grain 7 lies outside the cell's outer polygon"),
    "radius as text": (CELL, "radius = 0.5\n", 'radius = "0.5"\n', "'0.5' is not a number"),
    "surface with a face missing": (SPATIAL_CELL, "[1, 6, 10], ", "", "the outer triangles do not close an oriented "
                                    "surface"),  # volume 1.71 instead of 1.82
    "surface with a face turned": (SPATIAL_CELL, "[1, 6, 10]", "[1, 10, 6]", "do not close an oriented surface"),
    "sphere outside": (SPATIAL_CELL, "position = [-0.035, 0.025, -0.02]", "position = [-0.035, 0.025, 9.0]",
                       "grain 11 lies outside the cell's outer polyhedron"),
}


@pytest.mark.parametrize("case", sorted(INVALID_CELLS))
def test_a_cell_file_whose_boundary_labels_or_values_are_wrong_is_refused_in_one_line(case, tmp_path):
    source, old, new, message = INVALID_CELLS[case]
    path = edited(tmp_path, source, old, new, source.name)
    with pytest.raises(MesostructureError, match=message.replace("(", r"\(").replace(")", r"\)")) as caught:
        load_mesostructure(path)
    assert "\n" not in str(caught.value)


def test_a_cell_file_that_is_not_utf8_is_one_line_and_a_byte_order_mark_is_read(tmp_path):
    latin = tmp_path / "latin.toml"
    latin.write_bytes(CELL.read_text().replace('name = "dense', 'name = "caf\u00e9 dense').encode("latin-1"))
    with pytest.raises(MesostructureError, match=r"not UTF-8 text \(byte [0-9]+ is 0xe9\)"):
        load_mesostructure(latin)  # an AttributeError (exit 1) before
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + CELL.read_bytes())
    assert load_mesostructure(bom).name == load_mesostructure(CELL).name


@pytest.mark.parametrize("edit, message", [
    ({"contact_tolerance": float("nan")}, r"contact_tolerance = nan is outside \[0, 1e-3\)"),  # no overlap check then
    ({"version": 99}, "of version 99: this package reads 1"),
    ({"extra": 1}, "unknown key 'extra'"),
    ({"driven": [["no", "no"]] * 7}, "driven flags must be booleans"),  # read as True
    ({"pair_type": [300] * 15}, "malformed entry"),  # an OverflowError
])
def test_a_stored_cell_description_is_checked_as_a_file_is(edit, message):
    """Descriptions (databases, model metadata, checkpoints) were read with few checks."""
    from warp_hcell.mesostructures.files import describe, from_description  # noqa: PLC0415

    data = json.loads(describe(load_mesostructure(CELL)))
    assert from_description(json.dumps(data)).name == data["name"]
    with pytest.raises(MesostructureError, match=message):
        from_description(json.dumps({**data, **edit}))
