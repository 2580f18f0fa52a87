"""Parametric mesostructures and specs: geometry against shipped files and closed forms, errors."""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from warp_hcell.mesostructures.hcell import build_h_cell, plain_alpha0 as plain_h_cell_alpha0, pore_ratio
from warp_hcell.mesostructures.builders import (
    mesostructure_arg,
    parse_mesostructure,
    resolve_mesostructure,
    split_mesostructure_list,
)
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import describe, from_description, load_mesostructure
from warp_hcell.mesostructures.mesostructure import MesostructureError
from warp_hcell.dem.model import initial_contacts

DATA = Path(__file__).resolve().parents[1] / "warp_hcell" / "data"


def assert_same_geometry(a, b, atol=1e-12):
    np.testing.assert_allclose(a.radius, b.radius, rtol=0, atol=atol)
    np.testing.assert_allclose(a.position, b.position, rtol=0, atol=atol)
    np.testing.assert_allclose(a.cell_size, b.cell_size, rtol=0, atol=atol)
    assert a.driven.tolist() == b.driven.tolist()
    assert a.outer.tolist() == b.outer.tolist()
    assert dict(zip(map(tuple, a.pairs.tolist()), a.pair_label.tolist())) == \
        dict(zip(map(tuple, b.pairs.tolist()), b.pair_label.tolist()))


def test_unequal_spec_is_the_shipped_lateral_file():
    assert_same_geometry(resolve_mesostructure("hcell-unequal:alpha0=55,lateral=0.7"),
                         load_mesostructure(DATA / "h_cell_lateral_0.7D.toml"))


def test_fines_spec_at_the_pore_size_is_the_shipped_fine_grain_file():
    # the file's fine grain (radius 0.26091 m) just touches grains 2, 3, 5, 6 of the alpha0 = 35 deg cell
    ratio = 0.26091387708279157 / 0.5
    assert_same_geometry(resolve_mesostructure(f"hcell-fines:alpha0=35,ratio={ratio!r}"),
                         load_mesostructure(DATA / "h_cell_fine_grain.toml"))


def test_plain_spec_is_h_cell_bit_for_bit_and_takes_the_command_alpha0():
    meso = resolve_mesostructure("hcell", 50.0)
    ref = h_cell(50.0)
    assert np.array_equal(meso.position, ref.position) and np.array_equal(meso.cell_size, ref.cell_size)
    assert resolve_mesostructure("hcell:alpha0=40", 50.0).cell_size[1] == pytest.approx(2 * math.sin(math.radians(40)))


def test_pore_ratio_is_the_inscribed_radius_of_the_pore():
    # pore centre to grain 2 = sqrt((D/2)^2 + (D sin a)^2); minus r, over r (issue 12: 0.415 m at 50 deg, D = 1 m)
    for alpha in (40.0, 50.0, 55.0):
        s = math.sin(math.radians(alpha))
        assert pore_ratio(alpha) == pytest.approx(2.0 * math.sqrt(0.25 + s * s) - 1.0, rel=1e-12)
    assert 0.5 * pore_ratio(50.0) == pytest.approx(0.415, abs=5e-4)


def test_fine_grain_at_the_pore_size_touches_the_four_lateral_grains_and_is_free():
    meso = resolve_mesostructure(f"hcell-fines:alpha0=50,ratio={pore_ratio(50.0)!r}")
    assert meso.n_grains == 7 and meso.driven[6].tolist() == [False, False]
    touching = initial_contacts(meso.position[None], meso.radius[None], meso.pairs, 1e-9)[0]
    fine_pairs = {tuple(p) for p, c in zip(meso.pairs.tolist(), touching) if c and 6 in p}
    assert fine_pairs == {(1, 6), (2, 6), (4, 6), (5, 6)}
    small = resolve_mesostructure("hcell-fines:alpha0=50,ratio=0.5")
    with_fine = np.any(small.pairs == 6, axis=1)
    assert with_fine.sum() == 6
    assert not initial_contacts(small.position[None], small.radius[None], small.pairs, 1e-9)[0][with_fine].any()


def test_several_fine_grains_at_offsets():
    meso = resolve_mesostructure("hcell-fines:alpha0=55,ratio=0.3/0.2,n=0.4/-0.4,t=0")
    np.testing.assert_allclose(meso.position[6:], [[0.2, 0.0], [-0.2, 0.0]])
    np.testing.assert_allclose(meso.radius[6:], [0.15, 0.1])
    assert resolve_mesostructure("hcell-fines:alpha0=55,ratio=0/0.2").n_grains == 7


def test_plain_h_cell_is_recognised_and_nothing_else():
    assert plain_h_cell_alpha0(resolve_mesostructure("hcell:alpha0=50")) == (50.0, 0.5)
    assert plain_h_cell_alpha0(resolve_mesostructure("hcell-fines:alpha0=50,ratio=0")) == (50.0, 0.5)
    assert plain_h_cell_alpha0(h_cell(42.5, 1.0)) == (42.5, 1.0)
    assert plain_h_cell_alpha0(resolve_mesostructure("hcell-fines:alpha0=50,ratio=0.2")) is None
    assert plain_h_cell_alpha0(load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")) is None


def test_every_cell_with_h_cell_labels_declares_alpha0_and_the_observables():
    def alpha0(meso):
        return meso.parameters.get("alpha0_deg")

    assert alpha0(resolve_mesostructure("hcell-fines:alpha0=50,ratio=0.2")) == 50.0
    assert alpha0(resolve_mesostructure("hcell-unequal:alpha0=47.25,lateral=0.7")) == 47.25
    assert alpha0(load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")) == pytest.approx(55.0, abs=1e-9)
    assert [o.name for o in h_cell(50.0).observables] == ["alpha_deg", "d1", "d2", "N1", "N2", "T1", "closed1",
                                                          "closed2"]
    unlabelled = replace(h_cell(50.0), pair_label=None, observables=(), parameters={})
    assert alpha0(unlabelled) is None and plain_h_cell_alpha0(unlabelled) is None
    assert alpha0(from_description(describe(unlabelled))) is None
    assert from_description(describe(h_cell(50.0))).parameters == {"alpha0_deg": 50.0}


def test_split_list_keeps_spec_keys_together():
    assert split_mesostructure_list("hcell,hcell-fines:alpha0=50,ratio=0.7,a/b.toml,hcell-unequal:lateral=0.6") == [
        "hcell", "hcell-fines:alpha0=50,ratio=0.7", "a/b.toml", "hcell-unequal:lateral=0.6"]


@pytest.mark.parametrize("text, alpha0, message", [
    ("hcell-fines:alpha0=50,ratio=0.9", None, "mesostructure 'hcell-fines:alpha0=50,ratio=0.9': fine grain ratio 0.9 "
     "does not fit the pore at n=0, t=0: the largest is 0.829562 (alpha0 = 50 deg)"),
    ("hcell-fines:ratio=0.85", 50.0, "fine grain ratio 0.85 does not fit the pore"),
    ("hcell-fines:ratio=0.2,n=5", 50.0, "fine grain at n=5, t=0 (units of r) is outside the pore"),
    ("hcell-fines:ratio=0.3/0.3", 55.0, "grains 7 and 8 overlap by 0.3 m"),
    ("hcell-unequal:alpha0=31,lateral=1.5", None, "grains 2 and 6 overlap"),
    ("hcell-fines:ratio=0.2/0.2,n=1/2/3", 55.0, "n has 3 values for 2 fine grains"),
])
def test_geometry_errors_are_one_line(text, alpha0, message):
    with pytest.raises(MesostructureError, match=None) as info:
        resolve_mesostructure(text, alpha0)
    assert message in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("text, message", [
    ("hcell:foo=1", "mesostructure 'hcell:foo=1': unknown key 'foo' for hcell; allowed: alpha0, radius, lateral"),
    ("hcell-fines", "mesostructure 'hcell-fines': hcell-fines needs ratio=..."),
    ("hcell-unequal:alpha0=50", "hcell-unequal needs lateral=..."),
    ("hcell:alpha0=95", "alpha0 = 95 deg is outside [30, 90) deg"),
    ("hcell:alpha0=x", "alpha0='x' is not a number"),
    ("hcell:alpha0=50,alpha0=55", "key 'alpha0' given twice"),
    ("hcell:alpha0", "'alpha0' is not KEY=VALUE"),
    ("no/such/file.toml", "mesostructure 'no/such/file.toml' is neither a file nor a spec"),
])
def test_syntax_errors_are_one_line_argparse_errors(text, message):
    with pytest.raises(argparse.ArgumentTypeError) as info:
        mesostructure_arg(text)
    assert message in str(info.value)


def test_files_and_specs_parse_to_sources():
    source = parse_mesostructure(str(DATA / "h_cell_lateral_0.7D.toml"))
    assert source.kind is None and not source.takes_alpha0 and source.label == "h_cell_lateral_0.7D"
    spec = parse_mesostructure("hcell-fines:ratio=0.5")
    assert spec.takes_alpha0 and spec.fixed_alpha0 is None
    assert parse_mesostructure("hcell-fines:alpha0=50,ratio=0.5").fixed_alpha0 == 50.0
    assert build_h_cell(50.0, fines=(0.5,)).n_grains == 7


def test_biaxial_cli_rejects_a_fine_grain_too_big_for_its_alpha0_before_running(tmp_path, capsys):
    from homogenization.cli import biaxial
    from warp_hcell.core.cli import run_main

    out = tmp_path / "run"
    code = run_main(biaxial.main, ["--backend", "dem", "--alpha0", "50", "--mesostructure", "hcell-fines:ratio=0.85",
                                   "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "fine grain ratio 0.85 does not fit the pore" in err
    assert not out.exists()


def test_cell_cli_runs_a_spec_like_the_file_it_describes(tmp_path):
    from homogenization.cli import cell
    from warp_hcell.core.cli import run_main

    path = tmp_path / "path.csv"
    path.write_text("d_eps_n,d_eps_t\n" + "2e-3,-1e-3\n" * 3)
    outs = []
    for name, meso in (("file", str(DATA / "h_cell_lateral_0.7D.toml")), ("spec", "hcell-unequal:lateral=0.7")):
        out = tmp_path / f"{name}.csv"
        assert run_main(cell.main, ["--backend", "dem", "--alpha0", "55", "--mesostructure", meso, "--path", str(path),
                                    "--positions", "--out", str(out)]) == 0
        outs.append(out.read_text())
    assert outs[0] == outs[1] and len(outs[0].splitlines()) == 4
