"""The default surrogate of a cell: the hybrid (network + exact equilibrium corrections) for a 3D
cell with fine grains, the network alone for any other; the ANN backend runs a model with the
corrections its certificate measured without flags; ``learn.json`` records the round flags."""

import json
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from model_copies import shipped_3d_copy

from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell3D
from homogenization.ann.envelope import has_fine_grains
from homogenization.ann.escalation import RELEASE_RULE, RELEASE_RULE_AFTER, RELEASE_RULES
from homogenization.cli import learn as learn_cli
from homogenization.cli import train as train_cli
from homogenization.learning.settings import (default_equilibrium, FINES_EQUILIBRIUM_CORRECTIONS,
                                              FINES_EQUILIBRIUM_TOLERANCE)
from training.config import HYBRID_EPOCHS, HYBRID_PATIENCE, TrainConfig
from warp_hcell.core.cli import UserError
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.database.format import FORMAT, FORMAT_VERSION
from warp_hcell.mesostructures.builders import mesostructure_arg
from warp_hcell.mesostructures.files import describe, load_mesostructure

ROOT = Path(__file__).resolve().parents[1]
CELLS = ROOT / "benchmarks" / "cells"
SHIPPED_3D = default_model_path(3)
needs_model = pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")


def _meso(spec: str):
    return mesostructure_arg(spec).build()


@pytest.mark.parametrize("spec", ["hcell3d-fines:alpha0=55,ratio=0.9", "hcell3d-fines:alpha0=53,ratio=0.74,n=0.06,t2=0.04"])
def test_a_3d_cell_with_a_fine_grain_defaults_to_the_hybrid(spec):
    meso = _meso(spec)
    assert has_fine_grains(meso)
    assert default_equilibrium(meso) == (FINES_EQUILIBRIUM_CORRECTIONS, FINES_EQUILIBRIUM_TOLERANCE) == (20, 1e-4)


@pytest.mark.parametrize("name", ["fine_off_centre", "unequal_planes", "large_axial"])
def test_the_committed_acceptance_cells_are_3d_cells_with_a_fine_grain(name):
    meso = load_mesostructure(CELLS / f"{name}.toml")
    assert meso.dim == 3 and meso.n_grains == 11
    assert default_equilibrium(meso) == (20, 1e-4)


@pytest.mark.parametrize("spec", ["hcell3d:alpha0=55", "hcell3d:alpha0=55,lateral=0.8", "hcell:alpha0=50",
                                  "hcell-fines:alpha0=50,ratio=0.82", "hcell-unequal:lateral=0.7"])
def test_plain_and_planar_cells_keep_the_network_alone(spec):
    assert default_equilibrium(_meso(spec)) == (0, None)
    assert not has_fine_grains(_meso(spec)) or _meso(spec).dim == 2


def _database(path: Path, spec: str) -> Path:
    """A file that ``hmodel train`` reads as a database of ``spec``'s cells before any training."""
    meso = _meso(spec)
    with h5py.File(path, "w") as f:
        f.attrs["format"], f.attrs["format_version"] = FORMAT, FORMAT_VERSION
        f.attrs["mesostructure"] = describe(meso)
        f["d_eps"] = [[0.0] * meso.dim]
    return path


def _train_args(tmp_path, *flags):
    return train_cli.build_parser().parse_args(["--data", str(tmp_path / "db.h5"), "--out", str(tmp_path / "m.pt"), *flags])


def test_train_certifies_the_hybrid_of_a_fines_database_and_trains_its_network_shorter(tmp_path):
    _database(tmp_path / "db.h5", "hcell3d-fines:alpha0=55,ratio=0.9")
    args = _train_args(tmp_path)
    measured = train_cli.surrogate_of(args)
    assert (measured.equilibrium_corrections, measured.equilibrium_tolerance) == (20, 1e-4)
    assert (args.epochs, args.patience) == (HYBRID_EPOCHS, HYBRID_PATIENCE) == (30, 10)
    overridden = _train_args(tmp_path, "--equilibrium-corrections", "0")
    measured = train_cli.surrogate_of(overridden)
    assert measured.equilibrium_corrections == 0 and measured.equilibrium_tolerance is None
    assert train_cli.training_command.config_of(overridden).epochs == TrainConfig().epochs == 300
    chosen = _train_args(tmp_path, "--equilibrium-corrections", "2", "--epochs", "7")
    measured = train_cli.surrogate_of(chosen)
    assert (measured.equilibrium_corrections, measured.equilibrium_tolerance, chosen.epochs, chosen.patience) == (2, None, 7, 10)


@pytest.mark.parametrize("spec", ["hcell3d:alpha0=55", "hcell:alpha0=50", "hcell-fines:alpha0=50,ratio=0.82"])
def test_train_keeps_the_network_alone_and_the_training_defaults_elsewhere(tmp_path, spec):
    _database(tmp_path / "db.h5", spec)
    args = _train_args(tmp_path)
    assert train_cli.surrogate_of(args).equilibrium_corrections == 0
    assert train_cli.training_command.config_of(args) == TrainConfig()


@needs_model
def test_a_run_takes_the_corrections_its_certificate_measured_without_flags(tmp_path):
    model, meta = shipped_3d_copy(tmp_path)
    assert AnnCell3D(ContactLaw(), 0.5, model=SHIPPED_3D).equilibrium_corrections == 0  # the network alone, as certified
    meta["certificate"]["settings"].update(equilibrium_corrections=2, equilibrium_tolerance=1e-3)
    model.with_suffix(".json").write_text(json.dumps(meta))
    cell = AnnCell3D(ContactLaw(), 0.5, model=model)
    assert (cell.equilibrium_corrections, cell.force_tolerance, cell.certificate_problem) == (2, 1e-3, None)
    assert cell.escalation is None  # a certificate that records no DEM escalation measured the hybrid without it
    escalated = AnnCell3D(ContactLaw(), 0.5, model=model, dem_escalation=True).certificate_problem
    assert escalated is not None and "without the DEM's increment" in escalated
    for rule, covered in ((None, False), ("a grain that moved and overlaps nothing", False), (RELEASE_RULE, True),
                          (RELEASE_RULE_AFTER, True)):
        meta["certificate"]["settings"].update(dem_escalation=True, dem_escalation_rule=rule)
        model.with_suffix(".json").write_text(json.dumps(meta))
        cell = AnnCell3D(ContactLaw(), 0.5, model=model, dem_escalation=True)
        problem = cell.certificate_problem
        assert (problem is None) == covered and (covered or "by another rule" in problem)
        if covered:  # the cell runs the rule its certificate measured, and no other one is covered by it
            assert cell.release_rule == rule
            other = next(r for r in RELEASE_RULES if r != rule)
            problem = AnnCell3D(ContactLaw(), 0.5, model=model, dem_escalation=True, release_rule=other).certificate_problem
            assert problem is not None and "by another rule" in problem
    meta["certificate"]["settings"].update(dem_escalation=False)
    del meta["certificate"]["settings"]["dem_escalation_rule"]
    model.with_suffix(".json").write_text(json.dumps(meta))
    assert AnnCell3D(ContactLaw(), 0.5, model=model, equilibrium_tolerance=1e-4).certificate_problem is not None
    alone = AnnCell3D(ContactLaw(), 0.5, model=model, equilibrium_corrections=0).certificate_problem
    assert alone is not None and "not the network alone" in alone

    run = [sys.executable, "-m", "homogenization.hmodel", "triaxial", "--backend", "ann", "--model", str(model),
           "--p0", "2e5", "--undrained", "--eps-max", "0.003", "--increment", "1e-3", "--order", "3", "--spins", "1"]
    done = subprocess.run([*run, "--out", str(tmp_path / "run")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "certificate passed" in done.stdout and "equilibrium corrections" in done.stdout
    refused = subprocess.run([*run, "--equilibrium-corrections", "0", "--out", str(tmp_path / "alone")], cwd=ROOT,
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2 and "not the network alone" in refused.stderr


def _learn_args(tmp_path, *flags):
    return learn_cli.build_parser().parse_args(["--mesostructure", "hcell3d-fines:alpha0=55,ratio=0.9",
                                                "--out", str(tmp_path / "run"), *flags])


def test_learn_json_records_the_round_flags_and_the_surrogate(tmp_path):
    args = _learn_args(tmp_path, "--stall-rounds", "3", "--departure-margin", "0.25", "--max-database-mb", "80")
    meso = args.mesostructure.build()
    options = learn_cli._options(args, meso, learn_cli.certificate_settings(args, meso))
    assert (options["stall_rounds"], options["departure_margin"], options["max_database_mb"]) == (3, 0.25, 80.0)
    assert (options["equilibrium_corrections"], options["equilibrium_tolerance"]) == (20, 1e-4)
    config = learn_cli._train_config(args, learn_cli.certificate_settings(args, meso))
    assert (config.epochs, config.patience) == (HYBRID_EPOCHS, HYBRID_PATIENCE)

    out = tmp_path / "run"
    out.mkdir()
    (out / "learn.json").write_text(json.dumps(options))
    with pytest.raises(UserError, match="other options"):
        learn_cli.main(["--mesostructure", "hcell3d-fines:alpha0=55,ratio=0.9", "--out", str(out), "--stall-rounds", "2",
                        "--departure-margin", "0.25", "--max-database-mb", "80"])
    assert json.loads((out / "learn.json").read_text()) == options and sorted(p.name for p in out.iterdir()) == ["learn.json"]


def test_a_learn_json_without_the_round_flags_reads_as_their_defaults(tmp_path):
    args = _learn_args(tmp_path)
    meso = args.mesostructure.build()
    options = learn_cli._options(args, meso, learn_cli.certificate_settings(args, meso))
    older = {k: v for k, v in options.items() if k not in learn_cli.ROUND_OPTIONS}
    (tmp_path / "learn.json").write_text(json.dumps(older))
    assert learn_cli._recorded(tmp_path / "learn.json") == options
