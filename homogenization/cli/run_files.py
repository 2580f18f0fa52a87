"""What the commands that run backends share: the backend flags, the flags given, the output
folder, the parameters and the status line of each backend's run.

- ``backend_options``, ``check_options``, ``check_models_take``: the flags that go to some
  backends only (``BACKEND_ONLY_OPTIONS``, ``DEVICE_BACKENDS``) and the backends' cells;
- ``check_run(args, figure_file)``: what a run command checks before any work;
- ``explicit_flags(parser, argv, dests)``: the flags of a built-in programme that the user set;
  ``refuse_programme_flags(parser, argv, flags)``: none of them with --programme;
  ``shear_iso_increment(args, hint)``: the built-in programme's increments checked, and its
  isotropic increment (``options.add_programme_arguments``);
- ``resolve_void_ratio(args, argv, parser, dim)``: --void-ratio checked and turned into --alpha0
  by the void-ratio map (the commands pass it and --void-ratio to ``driver.run``);
- ``check_replaceable(out, figure_file)``: DIR holds nothing but what the command writes;
- ``backend_parameters(...)``: the first entries of a run's stored parameters (backend, its
  options and provenance, contact law, radius, alpha0);
- ``write_backend_run(...)``: run.h5 and curve.csv of one backend, and its status line;
- ``build_models(...)`` and ``run_backends(...)``: every backend built and checked before any
  run (an ANN model without a passed certificate refused unless --uncertified-ok), then run,
  stored and reported one after the other; ``envelope_note``: where an ANN run left its
  certificate's envelope (one warning, the status line, run.h5's ``ann_model.outside_envelope``);
- ``run_checkpoints(...)``: each backend's checkpoint in ``.OUT.resume`` (``element_test.checkpoint``), from
  which the same command resumes an interrupted run; ``checkpoint_folder(out)`` is removed after a finished one;
  ``resumable(out, checkpoints)``: an interruption inside says so.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import shutil
import sys
import time
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from homogenization.element_test import driver
from homogenization.output import io
from homogenization.backends import backend_class, BACKENDS, make_cell_model
from homogenization.element_test import programme as programmes
from homogenization.cli.options import ISO_TO_SHEAR_INCREMENT, certificate_note, refuse_uncertified
from homogenization.element_test.driver import Record
from homogenization.material.density import DensityMap, default_map
from homogenization.ann.envelope import summary as envelope_summary
from warp_hcell.core.cli import quiet_warp, say, UserError, writing_to
from warp_hcell.core.files import TEMPORARY_SUFFIX, check_output_path
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.mesostructures.mesostructure import Mesostructure


BACKEND_ONLY_OPTIONS = {"threads": ("dem", "ann"), "model": ("ann",), "equilibrium_corrections": ("ann",),
                        "equilibrium_tolerance": ("ann",)}
"""Backend-specific flags (argparse dest) -> the backends that take them (a command may lack some of them)."""
DEVICE_BACKENDS = ("dem", "ann")
"""Backends that take --device; the analytical cell runs on the cpu."""


def backend_options(args: argparse.Namespace, name: str) -> dict[str, Any]:
    """Keyword options for backend ``name``: only the flags it takes and the user set."""
    options: dict[str, Any] = {}
    if name in DEVICE_BACKENDS:
        options["device"] = args.device
    for dest, takers in BACKEND_ONLY_OPTIONS.items():
        value = getattr(args, dest, None)
        if value is not None and name in takers:
            options[dest] = value
    return options


def check_models_take(models: dict[str, Any], meso: Mesostructure) -> None:
    """UserError (one line) unless every backend builds a cell of ``meso`` (checked before any run)."""
    for name, model in models.items():
        try:
            model.init_state(meso, 1)
        except ValueError as exc:
            raise UserError(f"{name}: {exc}") from None


def check_options(args: argparse.Namespace, backends: Sequence[str] | None = None) -> None:
    """One-line UserError for flags that no chosen backend takes; fail early on unbuilt backends.

    ``backends``: the chosen backend names (None: ``args.backend``, a ``backend_list``).
    """
    backends = tuple(args.backend if backends is None else backends)
    for dest, takers in BACKEND_ONLY_OPTIONS.items():
        if getattr(args, dest, None) is not None and not set(takers) & set(backends):
            flag = "--" + dest.replace("_", "-")
            raise UserError(f"{flag} applies to --backend {' or '.join(takers)} only")
    if getattr(args, "equilibrium_tolerance", None) is not None and getattr(args, "equilibrium_corrections", None) is None:
        raise UserError("--equilibrium-tolerance applies with --equilibrium-corrections only")
    if args.device != "cpu" and not set(DEVICE_BACKENDS) & set(backends):
        raise UserError(f"--device applies to --backend {' or '.join(DEVICE_BACKENDS)} only (analytical runs on the cpu)")
    for name in backends:
        backend_class(name)  # ValueError (one line) if the backend is not built in this version
    if args.device != "cpu" and "ann" in backends:
        import torch  # noqa: PLC0415 (only when the ANN is asked for a GPU)

        if not torch.cuda.is_available():
            raise UserError(f"--device {args.device}: the installed torch has no CUDA support; use --device cpu for the ann")


def check_run(args: argparse.Namespace, figure_file: str, *extra_files: str) -> None:
    """What a run command checks before any work: --out (``check_output_path``,
    ``check_replaceable``; ``extra_files``: other files the command writes there) and the
    backend-only flags (``check_options``); Warp's start-up lines are silenced for the DEM backend where
    --verbose is not given (for the ANN's hybrid: ``build_models``)."""
    if "dem" in args.backend and not args.verbose:
        quiet_warp(args.device)
    check_output_path(args.out, overwrite=args.overwrite)
    check_replaceable(args.out, figure_file, *extra_files)
    check_options(args)


def explicit_flags(parser: argparse.ArgumentParser, argv: Sequence[str], dests: Sequence[str]) -> set[str]:
    """The argparse dests among ``dests`` that ``argv`` sets explicitly (not by default).

    ``parser`` is a fresh parser of the command (its defaults are replaced here).
    """
    unset = object()  # not a string, so argparse does not run it through type=
    parser.set_defaults(**{dest: unset for dest in dests})
    parsed = vars(parser.parse_args(argv))
    return {dest for dest in dests if parsed.get(dest, unset) is not unset}


def warn_unused_alpha0(parser: argparse.ArgumentParser, argv: Sequence[str], source: Any) -> None:
    """A ``UserWarning`` (one line) where ``argv`` gives --alpha0 but the cell ``source`` (``--mesostructure``, None:
    the H-cell of --alpha0) does not take it: a file, or a spec with its own alpha0."""
    if source is None or "alpha0" not in explicit_flags(parser, argv, ("alpha0",)):
        return
    if source.kind is not None and "alpha0" not in dict(source.options):
        return
    warnings.warn(f"--alpha0 is not used: --mesostructure {source.text} gives its own opening angle", UserWarning,
                  stacklevel=2)


def refuse_programme_flags(parser: argparse.ArgumentParser, argv: Sequence[str], flags: dict[str, str]) -> None:
    """UserError (one line) naming the flags of the built-in programme (``flags``: argparse dest ->
    flag) that ``argv`` sets along with --programme; ``parser`` is a fresh parser of the command."""
    explicit = explicit_flags(parser, argv, tuple(flags))
    given = [flag for dest, flag in flags.items() if dest in explicit]
    if given:
        raise UserError(f"{', '.join(given)} do not apply with --programme (the file holds the whole programme)")


def resolve_void_ratio(args: argparse.Namespace, argv: Sequence[str], parser: argparse.ArgumentParser,
                       dim: int) -> DensityMap | None:
    """The void-ratio map of a run given --void-ratio (``options.add_void_ratio_arguments``; its e_min and
    e_max where --posterior set them, ``posterior_flags.apply_posterior``), with --alpha0 set to the map's
    opening angle; None without --void-ratio.

    Raises:
        UserError: one line, before any run: --void-ratio with --alpha0 or a --mesostructure that
            fixes its own alpha0; --e-min/--e-max without --void-ratio or not
            e_min < e_max; a void ratio outside [e_min, e_max].
    """
    explicit = explicit_flags(parser, argv, ("alpha0", "e_min", "e_max"))
    if args.void_ratio is None:
        if explicit & {"e_min", "e_max"}:
            raise UserError("--e-min and --e-max apply with --void-ratio only")
        return None
    if "alpha0" in explicit:
        raise UserError("--void-ratio sets alpha0 through the void-ratio map; give --void-ratio or --alpha0, not both")
    spec = getattr(args, "mesostructure", None)
    if spec is not None and not spec.takes_alpha0:
        raise UserError(f"--void-ratio sets alpha0, but --mesostructure {spec.text} fixes its own; give a builder "
                        f"spec without alpha0")
    try:
        density_map = default_map(dim, args.e_min, args.e_max)
    except ValueError as exc:
        raise UserError(f"--e-min {args.e_min:g} --e-max {args.e_max:g}: {exc}") from None
    args.alpha0 = density_map.alpha0_deg(density_map.check(args.void_ratio, "--void-ratio"))
    return density_map


def shear_iso_increment(args: argparse.Namespace, hint: str = "") -> float:
    """The isotropic strain increment [-] of a built-in programme (``options.add_programme_arguments``):
    --iso-increment, else ``ISO_TO_SHEAR_INCREMENT`` x --increment.

    Raises:
        UserError: --increment larger than --eps-max (``hint`` ends the line: the shear stage
            would be one increment), or an isotropic increment of at least
            ``programme.ISO_MAX_STRAIN``.
    """
    if args.increment > args.eps_max:
        raise UserError(f"--increment {args.increment:g} is larger than --eps-max {args.eps_max:g}{hint}")
    iso_increment = getattr(args, "iso_increment", ISO_TO_SHEAR_INCREMENT * args.increment)
    if iso_increment >= programmes.ISO_MAX_STRAIN:
        raise UserError(f"--iso-increment {iso_increment:g} must be < {programmes.ISO_MAX_STRAIN:g}, "
                        f"the largest isotropic strain allowed")
    return iso_increment


def check_replaceable(out: Path, figure_file: str, *extra_files: str) -> None:
    """UserError unless ``out`` is absent or holds only what a run command writes.

    A run command writes run.h5, curve.csv, ``figure_file``, ``extra_files`` and one folder per backend;
    --overwrite replaces the whole folder, so it must not hold anything else (``--out .``
    with --overwrite would otherwise delete the working folder).
    """
    if not out.is_dir():
        if out.exists():
            raise UserError(f"--out {out} is a file; give a folder")
        return
    ours = {io.RUN_FILE, io.CURVE_FILE, figure_file, *extra_files, *BACKENDS}
    foreign = sorted(p.name for p in out.iterdir() if p.name not in ours)
    if foreign:
        raise UserError(f"{out} holds files that this command did not write ({', '.join(foreign[:3])}); "
                        f"choose another --out")


def provenance_of(name: str, model: Any, options: dict[str, Any]) -> dict[str, Any]:
    """Backend settings worth recording: DEM settings and threads; the ANN's model path and
    sha256, its certificate (worst figure, certified, the problem where not: of the file, or of the
    run's cells, ``AnnCell.certificate_problem``; a model run with equilibrium corrections records
    their number and tolerance, and no certificate of the network alone covers it), its
    out-of-distribution counts (cell-increments checked and outside the threshold) and, where its fused
    step ran compiled, which code ran it (``compiled_step``: "precompiled" with its loader, or "numba" with the reason)."""
    record: dict[str, Any] = {}
    if hasattr(model, "settings"):
        record["dem_settings"] = asdict(model.settings)
    if hasattr(model, "threads"):
        record["dem_threads"] = int(model.threads)
    if name == "ann":
        from homogenization.ann.policy import model_record  # noqa: PLC0415

        record["ann_model"] = model_record(getattr(model, "model_path", None) or options.get("model"), model.metadata,
                                           model.equilibrium_corrections, model.force_tolerance,
                                           getattr(model, "escalation", None) is not None)
        if model.certificate_problem is not None:  # also the run's own cells, e.g. kinematics the certificate did not drive
            record["ann_model"].update(certified=False, certificate_problem=model.certificate_problem)
        corrections = getattr(model, "equilibrium_corrections", 0)
        if corrections:
            record["ann_model"].update(equilibrium_corrections=corrections, equilibrium_tolerance=model.force_tolerance,
                                       dem_escalation=model.escalation is not None)
        if model.ood is not None:
            record["ann_model"]["ood"] = {"checked": int(model.ood_counts[1]), "outside": int(model.ood_counts[0]),
                                          "threshold": model.ood.threshold}
        path = getattr(getattr(model, "fast", None), "step_path", None)
        if path is not None:  # the fused step ran: precompiled (training.precompiled) or numba's fallback
            record["ann_model"]["compiled_step"] = {"path": path, **({"reason": model.fast.precompiled_reason}
                                                                     if path == "numba" else
                                                                     {"loader": model.fast.precompiled_loader})}
    return record


def backend_parameters(name: str, model: Any, options: dict[str, Any], law: ContactLaw, radius: float,
                       meso: Mesostructure) -> dict[str, Any]:
    """The stored parameters every run starts with, in this order: backend, backend_options
    (paths as text), the backend's provenance, contact_law, radius [m], alpha0_deg (None for a
    cell that declares none)."""
    return {
        "backend": name,
        "backend_options": {k: str(v) if isinstance(v, Path) else v for k, v in options.items()},
        **provenance_of(name, model, options),
        "contact_law": law.to_dict(),
        "radius": radius,
        "alpha0_deg": meso.parameters.get("alpha0_deg"),
    }


def write_backend_run(work: Path, out: Path, name: str, record: Record, parameters: dict[str, Any], *,
                      several: bool, seed: int, command: str, elapsed: float, note: str = "") -> str:
    """Write run.h5 and curve.csv of backend ``name`` into ``work`` (``work/name`` when
    ``several``); returns its status line, with the final paths under ``out``.

    The line counts the cell-increments the backend reports unconverged
    (``diagnostics["n_unconverged"]``) and those with contacts outside the closed form
    (``diagnostics["n_cross_plane"]``), where there are any, the ANN's equilibrium corrections
    (``n_corrections`` Newton steps, ``n_shortened`` of them shortened by the line search and
    ``n_shifted`` shifted, in ``n_corrected`` cell-increments) where it took them, the cell-increments with a
    released grain (``n_released``) and those handed to the DEM (``n_escalated``) where it may, then
    ``note`` (the backend's own).

    Raises:
        UserError: the folder cannot be written (one line).
    """
    folder = work / name if several else work
    final = out / name if several else out
    with writing_to(out):
        io.write_run(folder, record, parameters=parameters, seed=seed, command=command)
    unconverged = record.diagnostics.get("n_unconverged")
    counts = (f", {int(unconverged.sum())} unconverged cell-increments"
              if unconverged is not None and unconverged.sum() else "")
    cross = record.diagnostics.get("n_cross_plane")
    if cross is not None and cross.sum():
        counts += f", cross-plane contacts outside the closed form in {int(cross.sum())} cell-increments"
    corrected = record.diagnostics.get("n_corrected")
    if corrected is not None:
        shortened, shifted = record.diagnostics.get("n_shortened"), record.diagnostics.get("n_shifted")
        counts += (f", equilibrium corrections: {int(np.nansum(record.diagnostics['n_corrections']))} Newton steps"
                   + (f" ({int(np.nansum(shortened))} shortened by the line search, {int(np.nansum(shifted))} shifted)"
                      if shortened is not None and shifted is not None else "")
                   + f" in {int(np.nansum(corrected))} cell-increments")
    released = record.diagnostics.get("n_released")
    if released is not None:
        counts += f", {int(np.nansum(released))} cell-increments with a released grain taken again from rest"
    escalated = record.diagnostics.get("n_escalated")
    if escalated is not None and np.nansum(escalated):
        counts += f", {int(np.nansum(escalated))} cell-increments handed to the DEM"
    return f"{name}: {record.n_increments} increments in {elapsed:.1f} s{counts}{note} -> {final / io.RUN_FILE}, {final / io.CURVE_FILE}"


def backend_note(model: Any) -> str:
    """A backend's own part of its status line: the ANN's certificate and out-of-distribution counts."""
    note = certificate_note(model)
    if getattr(model, "ood", None) is not None:
        note += f", out of distribution {int(model.ood_counts[0])} of {int(model.ood_counts[1])} checked cell-increments"
    return note


def envelope_note(model: Any, record: Record, meso: Mesostructure, stored: dict[str, Any]) -> str:
    """The ANN run's envelope check (``AnnCell.envelope_exits``): stored in ``stored`` (the run's
    ``ann_model`` parameters: ``envelope``, ``outside_envelope``, a list of phrases, empty inside,
    None uncertified); where the run left the envelope, one warning line on stderr, and the
    status line's note."""
    exits = model.envelope_exits(record.programme, meso)
    stored["envelope"], stored["outside_envelope"] = model.envelope, exits
    if not exits:
        return ""
    print(f"warning: ann: the run is {envelope_summary(exits)}", file=sys.stderr)
    return ", OUTSIDE its certificate's envelope (warning above)"


def build_models(args: argparse.Namespace, law: ContactLaw, meso: Mesostructure,
                 **model_options: Any) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """(model, options) of every --backend, by name; each built with ``law``, --radius,
    ``model_options`` and its own flags, and checked to build a cell of ``meso``, so that a
    missing model file or a mesostructure a backend does not model fails before any run. Warp's
    start-up lines are silenced (without --verbose) where an ANN hybrid may hand cells to the DEM
    (its ``escalation``); other ANN runs never import Warp."""
    options = {name: backend_options(args, name) for name in args.backend}
    models = {name: make_cell_model(name, contact_law=law, radius=args.radius, **model_options, **options[name])
              for name in args.backend}
    if not args.verbose and any(getattr(model, "escalation", None) is not None for model in models.values()):
        quiet_warp(args.device)
    check_models_take(models, meso)
    for model in models.values():
        refuse_uncertified(model, args)
    return models, options


CHECKPOINT_TAG = "resume"
"""The hidden folder ``.OUT.resume`` next to --out holds a run's checkpoints, one ``BACKEND.h5`` per backend."""
_NOT_IN_KEY = ("quiet", "verbose", "overwrite", "restart", "checkpoint_seconds", "out", "deviator", "fourth_panel",
               "normalise", "csl", "uncertified_ok", "posterior_band")
"""Flags that change no run's arithmetic (the figure's, the band's, the output's, the verbosity, the certificate's
refusal): a resumed command may differ in them."""


_THREADS_KEEP_BITS = ("analytical", "dem")
"""Backends whose results do not depend on --threads (the DEM's cells are independent of the chunks its threads
step; tests/test_homogenization_backends_dem.py): their checkpoints resume under other --threads. The ANN's torch
tangent may not."""


def checkpoint_folder(out: Path) -> Path:
    """The folder of the checkpoints of the runs on ``out`` (``CHECKPOINT_TAG``)."""
    return Path(out).parent / f".{Path(out).name}.{CHECKPOINT_TAG}"


def _key_value(value: Any) -> Any:
    """A flag's value as the checkpoint key stores it: a file as its path and sha256 (e.g. --posterior), other
    paths and mesostructures as text, tuples as lists."""
    if isinstance(value, Path):
        return {"path": str(value), "sha256": hashlib.sha256(value.read_bytes()).hexdigest()} if value.is_file() \
            else str(value)
    if isinstance(value, (tuple, list)):
        return [_key_value(v) for v in value]
    return getattr(value, "text", value)


def run_checkpoints(args: argparse.Namespace, models: dict[str, Any], options: dict[str, dict[str, Any]],
                    law: ContactLaw, meso: Mesostructure, programme: programmes.Programme
                    ) -> dict[str, driver.RunCheckpoint]:
    """A checkpoint per backend in ``checkpoint_folder(--out)``, keyed on the flags that change the run, the
    programme and the backend's stored parameters (--checkpoint-seconds apart; --restart removes the folder first).

    Raises:
        UserError: (one line, before any run) a checkpoint there written by a command with other settings.
    """
    folder = checkpoint_folder(args.out)
    if args.restart and folder.exists():
        shutil.rmtree(folder)
    others = sorted(p.stem for p in folder.glob("*.h5") if p.stem not in models)
    if others:
        raise UserError(f"{folder} holds the checkpoint of an interrupted run of other backends ({', '.join(others)}): "
                        f"run that command again to resume it, or add --restart to discard it")
    for stale in folder.glob(f".*{TEMPORARY_SUFFIX}"):  # of a save that a kill -9 cut short
        stale.unlink()
    common = {"flags": {k: _key_value(v) for k, v in vars(args).items() if k not in _NOT_IN_KEY},
              "programme": programmes.to_dict(programme), "mesostructure_sha256": description_sha256(describe(meso))}
    checkpoints = {}
    for name, model in models.items():
        backend = backend_parameters(name, model, options[name], law, args.radius, meso)
        key = {**common, "backend": backend, "model_files": _model_files(model)}
        if name in _THREADS_KEEP_BITS:  # resumed on other threads, the run is the same
            key["flags"] = {k: v for k, v in common["flags"].items() if k != "threads"}
            key["backend"] = {**{k: v for k, v in backend.items() if not k.endswith("threads")},  # (dem_threads)
                              "backend_options": {k: v for k, v in backend["backend_options"].items() if k != "threads"}}
        checkpoint = driver.RunCheckpoint(folder / f"{name}.h5", key, args.checkpoint_seconds)
        checkpoint.keep_last = name != list(models)[-1]
        if checkpoint.exists():
            try:
                checkpoint.check()
            except UserError as exc:
                advice = ("run that command again to resume it, or add --restart to discard it"
                          if "other settings" in str(exc) else "add --restart to discard it")
                raise UserError(f"{exc}: {advice}") from None
        checkpoints[name] = checkpoint
    return checkpoints


def _model_files(model: Any) -> dict[str, str]:
    """sha256 of the files of a model read from a file (``model_path``: its network, out-of-distribution index,
    certificate...: every file of its folder named after it); {} for other models."""
    path = getattr(model, "model_path", None)
    if path is None:
        return {}
    path = Path(path)
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.parent.glob(f"{path.stem}*"))
            if p.is_file()}


def run_backends(args: argparse.Namespace, models: dict[str, Any], options: dict[str, dict[str, Any]],
                 law: ContactLaw, meso: Mesostructure, run: Callable[[Any, driver.RunCheckpoint], Record],
                 parameters: Callable[[Record], dict[str, Any]], *, work: Path, command: str,
                 checkpoints: dict[str, driver.RunCheckpoint]
                 ) -> tuple[dict[str, Record], dict[str, dict[str, Any]], list[str]]:
    """Run every backend, one after the other, and write its run files into ``work``.

    Args:
        args: the command's arguments (--backend, --radius, --seed, --out).
        models, options: from ``build_models``.
        law, meso: the contact law and the cell of the run.
        run: ``run(model, checkpoint)`` -> the backend's ``driver.Record``, saved in and resumed from ``checkpoint``.
        checkpoints: by backend (``run_checkpoints``); a resumed one is said in a line.
        parameters: the command's stored parameters of a record, after ``backend_parameters``.
        work: the folder being written (``output_folder``); command: the command line stored.

    Returns:
        (records, stored parameters, status lines), by backend name.

    Raises:
        UserError: a ``driver.ControlError`` of a backend (one line naming it), or a folder
            that cannot be written.
    """
    records: dict[str, Record] = {}
    stored: dict[str, dict[str, Any]] = {}
    written: list[str] = []
    for name, model in models.items():
        start = time.perf_counter()
        resumed = checkpoints[name].exists()
        if resumed:
            done, stages = checkpoints[name].progress()
            say(f"{name}: resuming from {checkpoints[name].path} ({done} increments, {stages} stages finished)")
        try:
            record = run(model, checkpoints[name])
        except driver.ControlError as exc:
            raise UserError(f"{name}: {exc}") from None
        elapsed = time.perf_counter() - start
        stored[name] = {**backend_parameters(name, model, options[name], law, args.radius, meso),
                        **parameters(record)}
        note = backend_note(model) + (", resumed: the time is this process's" if resumed else "")
        if name == "ann":
            note += envelope_note(model, record, meso, stored[name]["ann_model"])
        written.append(write_backend_run(work, args.out, name, record, stored[name], several=len(models) > 1,
                                         seed=args.seed, command=command, elapsed=elapsed, note=note))
        records[name] = record
    return records, stored, written


@contextlib.contextmanager
def resumable(out: Path, checkpoints: dict[str, driver.RunCheckpoint]) -> Iterator[None]:
    """An interruption (Ctrl-C, ``kill``) inside says where the same command resumes from, where a checkpoint of
    ``checkpoints`` (``run_checkpoints(--out = out)``) is there: while the backends run and after (the band, the
    figure)."""
    try:
        yield
    except KeyboardInterrupt:
        if not any(checkpoint.exists() for checkpoint in checkpoints.values()):
            raise
        raise KeyboardInterrupt(f"the same command resumes from {checkpoint_folder(out)}") from None
