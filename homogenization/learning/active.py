"""Active learning of the meso-ANN: the DEM states where the certificate fails become new samples.

One round: the certificate (``homogenization.learning.certificate.certify``) runs the DEM
along its homogenised tests and keeps the DEM cell states met every ``state_every`` increments
(all orientations). The states of the tests that fail (max(dp, dq) > target) are probed as the
generator probes them (``warp_hcell.database.probing.compute_chunk``: the database's own
``DatabaseSettings``, so the same probe sizes, perturbed neighbours and zero probes), and the
samples are appended to the database (``append_samples``; layout in docs/database_format.md,
"Active-learning samples"): the per-sample datasets grow, ``source_round`` says which round a
sample comes from (0: the generator), the probed start states go to the group ``active_states``,
and the root attr ``active_learning`` lists the rounds. Each (test, orientation) of a round is a
path of its own (new ``path_id``), so training's split by path keeps a test's states together.

The loop (``learn``): train (``training.fitting.train_and_save`` with a ``TrainConfig``; from
random weights, or with ``ActiveSettings.warm_start`` from the kept model's,
``TrainConfig.init_from``), certify, and while the
certificate fails and the budget (``ActiveSettings``: rounds, samples, seconds, the database's
size ``max_database_mb``) is not spent, add a round and train a candidate beside the model. The
round rule: the candidate replaces the kept model only where its certificate is ``better``
(never worse: the kept worst never rises); a rejected round's samples stay in the database, and
the next round probes the kept model's failing tests again and restarts its training with the
next seed (``restarts``); ``rules_line`` counts what the rule did (a certificate within its target
but below the minimum certificate, ``homogenization.ann.envelope.MINIMUM``, is not passed, and no
round can mend it: the loop stops). A round probes the states of the failing tests (a test the
ANN could not follow, worst = inf, included; with ``departure_margin`` < 1 only those from where
the ANN left the DEM on, ``failing_states``: the certificate's ``departure``), and ``stall_rounds`` rounds without progress (``improved``: fewer
tests not followed, those followed further, or a lower worst) stop the loop with one line, as does a
certificate whose every failing test misses the DEM by no more than the DEM started from rest does (its
``dem_spread``: the target is finer than the reference resolves there, ``unresolvable_line``).
Every round is printed (samples added,
certificate worst, seconds) and stored in the model's JSON under ``active_learning``. With
``ActiveSettings.round_target`` the rounds go on past a pass while the worst test is above that stricter aim
(``short_of_aim``), probing the tests above it; the certificate's verdict stays that of its own target.

Layering: this module joins ``training`` and the DEM of ``warp_hcell``; neither imports it.
Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import h5py
import numpy as np

from homogenization.learning import certificate
from homogenization.learning.settings import ActiveSettings, CertificateSettings, release_rule_text
from homogenization.ann.envelope import equilibrium_settings, escalation_of, escalation_rule_of, verdict
from homogenization.ann.records import Certificate, learning_of, Round, with_learning
from training import fitting
from training.card import ModelCard, read_card, write_card
from training.config import TrainConfig
from training.network import n_features
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings, DemSettings
from warp_hcell.core.provenance import file_sha256
from warp_hcell.database import clean as cleaning
from warp_hcell.database import format as database
from warp_hcell.database.exploration import DEM_PREFIX
from warp_hcell.database.learning_state import free_coordinates
from warp_hcell.database.probing import compute_chunk, n_chunks, ProbeContext
from warp_hcell.mesostructures.files import from_description
from warp_hcell.mesostructures.mesostructure import Mesostructure

ACTIVE_STREAM = 0x61637476
"""First word of the seed of a round's probes (then the run's seed and the round)."""


WIDTH_LADDER: tuple[tuple[int, ...], ...] = ((40, 40), (48, 48))
"""Hidden widths a round may move to, cheapest first: those whose step of 360 H-cells was
measured no slower than the analytical step, the inference-speed bound of docs/ann.md (Speed),
with ``benchmarks/bench_ann.py --widths`` (docs/certificate.md, "Network size"; 3 x 40 and
2 x 56 exceeded it)."""
WIDEN_BELOW_GAIN = 2.0
"""A round whose certificate worst fell by less than this factor [-] from the round before
gives the next round the next rung of ``WIDTH_LADDER`` (samples alone stopped helping)."""


MIN_ROUND_SAMPLES = 1000
"""Fewest samples [-] a round adds: with less room left in the database budget the loop stops
(a round costs a training and a certificate whatever it adds)."""


def aim(cert: Certificate, settings: ActiveSettings) -> float:
    """The worst figure the rounds aim at [-]: the certificate's target, or ``settings.round_target`` where stricter."""
    return cert.target if settings.round_target is None else min(cert.target, settings.round_target)


def short_of_aim(cert: Certificate, settings: ActiveSettings) -> bool:
    """Whether rounds may still help ``cert``: it failed, or it passed with its worst above ``aim`` (a weak
    certificate, below the minimum, is no matter of samples)."""
    return verdict(cert) == "failed" or (verdict(cert) == "passed" and cert.worst > aim(cert, settings))


def failing_states(cert: Certificate, dem_states: Mapping[str, Mapping[str, np.ndarray]], margin: float = 1.0,
                   threshold: float | None = None) -> tuple[dict[str, np.ndarray], list[str]]:
    """The DEM states of the certificate's failing tests (max(dp, dq) > ``threshold``; None: the
    certificate's target), concatenated, and those tests' names. Of a test that records its
    ``departure`` (the increment where the ANN left the DEM, ``certificate.certify``; a test it
    could not follow included), only the states
    from ``departure - margin x n_increments`` on (``ActiveSettings.departure_margin``). States:
    ``cell_size`` (n, dim) [m], ``position`` (n, n_grains, dim) [m], ``shear_force`` (n, n_pairs)
    [N] (3D: (n, n_pairs, 3)), ``cell`` (n,) int64 (one id per test and orientation)."""
    threshold = cert.target if threshold is None else threshold
    tests = [t for t in cert.tests if t.figure > threshold and t.name in dem_states]
    if not tests:
        return {}, []
    keys = ("cell_size", "position", "shear_force", "cell")
    parts = []
    for test in tests:
        states = dem_states[test.name]
        keep = np.ones(states["cell"].shape[0], bool)
        if test.departure is not None and "increment" in states:
            keep = states["increment"] >= test.departure - margin * test.n_increments
        parts.append({k: states[k][keep] for k in keys})
    return {k: np.concatenate([part[k] for part in parts]) for k in keys}, [t.name for t in tests]


MIN_FOLLOWED_GAIN = 0.02
"""Progress of a round whose certificate has tests the ANN cannot follow (as many as the best round
before it): they are followed further, by at least this fraction of a test's increments, summed
over those tests [-] (``improved``)."""
MIN_WORST_GAIN = 0.1
"""Progress of a round whose ANN follows every test: its certificate worst is below the best
round's by at least this fraction of it [-] (``improved``)."""


def progress(entry: Round) -> tuple[int, float, float]:
    """(tests the ANN could not follow, the fractions of those tests it followed, summed,
    certificate worst) of a round's record (``round_entry``; one written without ``not_followed``
    counts an infinite worst as one test not followed)."""
    unfollowed = entry.not_followed if entry.not_followed is not None else (["?"] if math.isinf(entry.worst) else [])
    return len(unfollowed), float(entry.followed or 0.0), float(entry.worst)


def improved(new: Round, best: Round) -> bool:
    """Whether round record ``new`` made progress on ``best``: fewer tests the ANN cannot follow;
    or as many (some), followed further by ``MIN_FOLLOWED_GAIN``; or all followed and the worst
    ``MIN_WORST_GAIN`` lower."""
    (n_new, f_new, w_new), (n_best, f_best, w_best) = progress(new), progress(best)
    if n_new != n_best:
        return n_new < n_best
    if n_new:
        return f_new >= f_best + MIN_FOLLOWED_GAIN
    return w_new <= (1.0 - MIN_WORST_GAIN) * w_best


def best_round(rounds: Sequence[Round]) -> Round:
    """The round of ``rounds`` that the later ones did not improve on (``improved``)."""
    best = rounds[0]
    for entry in rounds[1:]:
        if improved(entry, best):
            best = entry
    return best


def stalled(rounds: Sequence[Round], settings: ActiveSettings) -> bool:
    """Whether the last ``settings.stall_rounds`` rounds made no progress on the best before them."""
    return len(rounds) > settings.stall_rounds and rounds[-1].round - best_round(rounds).round >= settings.stall_rounds


def stall_line(rounds: Sequence[Round], cert: Certificate, db: Path, margin: float = 1.0) -> str:
    """One line: why the loop stops without progress (which test, which rounds, what they tried;
    ``margin``: the rounds' ``ActiveSettings.departure_margin``)."""
    best, last = best_round(rounds), rounds[-1]
    tried = [r for r in rounds if r.round > best.round]
    test = cert.test(cert.worst_test)
    if math.isinf(cert.worst):
        where = (f"the ANN could not follow it past increment {_or_unknown(test.departure)} of "
                 f"{test.n_increments}: {_short(test.error or '')}")
    else:
        where = f"{100 * cert.worst:.3f} % off" + (f" from increment {test.departure} of {test.n_increments}"
                                                   if test.departure is not None else "")
    tests = sorted({name for r in tried for name in r.tests or []})
    widths = sorted({"x".join(map(str, r.hidden)) for r in tried if r.hidden is not None})
    return (f"active learning stops: no progress in rounds {tried[0].round}-{last.round} on round "
            f"{best.round} ({_figure(best)}): round {last.round} worst test {cert.worst_test!r}, {where}; "
            f"tried {sum(r.samples_added for r in tried)} samples on the DEM states of {', '.join(tests) or 'no test'}"
            f"{'' if margin >= 1.0 else f' from {margin:g} of a test before their departure on'}, network "
            f"{', '.join(widths) or '?'}; database {_mb(db):.1f} MB")


def unresolvable_line(cert: Certificate, threshold: float | None = None) -> str | None:
    """One line when no round can help: every test above ``threshold`` (None: the target) is off the DEM by no more
    than the DEM started from rest in every increment is (the test's ``dem_spread``, ``certificate.certify``), so
    that aim is finer than the reference resolves there; None otherwise (or where a test records no spread)."""
    threshold = cert.target if threshold is None else threshold
    failing = [t for t in cert.tests if t.figure > threshold]
    if not failing or any(t.dem_spread is None or not t.figure <= t.dem_spread for t in failing):
        return None
    figures = "; ".join(f"{t.name} {100 * t.figure:.3f} % against {100 * t.dem_spread:.3f} %" for t in failing)
    return (f"active learning stops: every failing test is off the DEM by no more than the DEM started from rest is "
            f"({figures}): the aim {100 * threshold:.3g} % is finer than the reference resolves there, "
            f"and no round of samples can close that; the certificate stays {verdict(cert)}")


def _figure(entry: Round) -> str:
    n, followed, worst = progress(entry)
    if n:
        return f"{n} test(s) not followed, {followed:.2f} of a test followed"
    return f"worst {100 * worst:.3f} %"


def _or_unknown(value: object) -> str:
    return "?" if value is None else str(value)


def _short(text: str, limit: int = 160) -> str:
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _mb(db: Path) -> float:
    return Path(db).stat().st_size / 1e6


BUDGET_MARGIN = 1.1
"""A round's samples are assumed to take this many times the bytes on disk of the file's average
sample [-] (a round's states are more loaded than the generator's average: counted at 1x, a round
on the tiny database of the tests ended 3 % over its budget)."""


def budget_room(db: Path, max_mb: float, reserve: int = 0) -> tuple[int, float]:
    """(samples that still fit in ``db`` under ``max_mb`` [MB] besides ``reserve`` bytes in memory
    (the round's probed states, stored at the file's own ratio of bytes on disk to bytes
    uncompressed, ``warp_hcell.database.format.sizes``), bytes on disk assumed per sample:
    ``BUDGET_MARGIN`` x ``warp_hcell.database.format.bytes_per_sample``)."""
    per_sample = BUDGET_MARGIN * database.bytes_per_sample(db)
    on_disk, raw = database.sizes(db)
    left = max_mb * 1e6 - on_disk - BUDGET_MARGIN * reserve * min(on_disk / max(raw, 1), 1.0)
    return max(int(left // per_sample), 0), per_sample


def round_seed(seed: int, round_index: int) -> int:
    """Seed of the probes of round ``round_index`` (independent of the generator's streams)."""
    return int(np.random.SeedSequence([ACTIVE_STREAM, int(seed), int(round_index)]).generate_state(1, np.uint64)[0])


def _physics(attrs: Mapping[str, Any]) -> tuple[ContactLaw, DemSettings, DatabaseSettings]:
    law = ContactLaw.from_flags(kn=float(attrs["kn"]), phi_g_deg=float(attrs["phi_g_deg"]), kt=float(attrs["kt"]))
    fields = {f.name for f in dataclasses.fields(DemSettings)}
    dem = DemSettings(**{k: v for k, v in json.loads(str(attrs.get("dem_settings", "{}"))).items() if k in fields})
    generator = json.loads(str(attrs["generator"])) if "generator" in attrs else {}
    fields = {f.name for f in dataclasses.fields(DatabaseSettings)}
    generator = {k: (tuple(v) if isinstance(v, list) else v) for k, v in generator.items() if k in fields}
    return law, dem, DatabaseSettings(**generator)


def probe_states(meso: Mesostructure, states: Mapping[str, np.ndarray], n_samples: int, seed: int,
                 attrs: Mapping[str, Any], threads: int = 1) -> dict[str, np.ndarray]:
    """``n_samples`` probes of the DEM ``states`` (``failing_states``), as the generator probes
    (the database's ``generator`` settings, its contact law and DEM settings from ``attrs``);
    ``path_id`` is the state's ``cell``. Returns ``compute_chunk``'s arrays, all chunks concatenated."""
    from warp_hcell.dem.cell import DemCell  # noqa: PLC0415 (Warp loads only where cells are stepped)

    law, dem_settings, generator = _physics(attrs)
    settings = dataclasses.replace(generator, samples=int(n_samples))
    n = states["cell_size"].shape[0]
    context = ProbeContext(
        cell_model=DemCell(law, float(meso.radius.mean()), settings=dem_settings, threads=threads), meso=meso,
        schema=meso.schema(), contact_law=law, contact_tolerance=dem_settings.contact_tolerance,
        states={DEM_PREFIX + "cell_size": states["cell_size"], DEM_PREFIX + "position": states["position"],
                DEM_PREFIX + "shear_force": states["shear_force"], "path_id": states["cell"],
                **{name: np.full(n, value) for name, value in meso.parameters.items()}})
    chunks = [compute_chunk(context, settings, seed, c) for c in range(n_chunks(settings))]
    return {name: np.concatenate([chunk[name] for chunk in chunks]) for name in chunks[0]}


def append_samples(path: Path, samples: Mapping[str, np.ndarray], states: Mapping[str, np.ndarray],
                   record: Mapping[str, Any]) -> dict[str, Any]:
    """Append one round's ``samples`` (``probe_states``) and their start ``states``
    (``failing_states``) to database ``path`` (``warp_hcell.database.format.append_round``, with
    the free coordinates of the file's mesostructure and the cleaning rules of
    ``warp_hcell.database.clean``); returns the round's record as stored in ``active_learning``.

    Raises:
        ValueError: (one line) ``samples`` lacks a per-sample dataset of the file.
    """
    schema = from_description(str(_attrs(path)["mesostructure"])).schema()
    start = {"cell_size": states["cell_size"], "free_position": free_coordinates(schema, states["position"]),
             "shear_force": states["shear_force"], "path_id": states["cell"]}
    return database.append_round(path, samples, start, record, clean=lambda new: cleaning.clean_samples(new)[0])


def _certify(model: Path, card: ModelCard, measured: CertificateSettings, settings: ActiveSettings, threads: int
             ) -> tuple[Certificate, dict[str, dict[str, np.ndarray]]]:
    states: dict[str, dict[str, np.ndarray]] = {}
    cert = certificate.certify(model, card=card, dem_states=states, state_every=settings.state_every, threads=threads,
                               **measured.keywords())
    return cert, states


def _current(cert: Certificate | None, model: Path, measured: CertificateSettings, dim: int) -> bool:
    """Whether ``cert`` was measured on this model file with the certificate settings ``measured``
    (the equilibrium corrections included: ``envelope.equilibrium_settings``, and the released-grain rule of a
    hybrid that has one) on cells of dimension ``dim``."""
    if cert is None or cert.model_sha256 != file_sha256(model):
        return False
    wanted = certificate.requested_settings(dim, pressures=measured.pressures, eps_max=measured.eps_max,
                                            n_orientations=measured.n_orientations, spatial_rule=measured.spatial_rule)
    wanted.pop("increment")
    hybrid = ((measured.equilibrium_corrections, measured.equilibrium_tolerance or DemSettings().force_tolerance)
              if measured.equilibrium_corrections else (0, None))
    same_rule = not escalation_of(cert) or escalation_rule_of(cert) == release_rule_text(measured.release_rule)
    return (all(cert.settings.get(k) == v for k, v in wanted.items()) and cert.target == measured.target
            and equilibrium_settings(cert) == hybrid and same_rule)


def _record(model: Path, card: ModelCard, rounds: list[Round], cert: Certificate) -> ModelCard:
    """``card`` with the certificate and the rounds, written as the model's JSON (atomically); returns it."""
    card = with_learning(card, cert, rounds)
    write_card(model, card)
    return card


def round_line(entry: Round) -> str:
    """One line of a round's report."""
    capped = entry.samples_capped
    return (f"active round {entry.round}: +{entry.samples_added} samples ({entry.samples_total} in all"
            + (f"; {capped} more did not fit the database budget" if capped else "") + "), "
            f"certificate worst {100 * entry.worst:.3f} % ({entry.worst_test}), "
            f"{(entry.verdict or ('passed' if entry.passed else 'failed')).upper()}, {entry.seconds:.1f} s"
            + (f", database {entry.database_mb:.1f} MB ({entry.database_raw_mb:.1f} MB uncompressed)"
               if entry.database_mb is not None else "")
            + (f" (training {'x'.join(map(str, entry.hidden))}, {entry.epochs} epochs"
               f"{', warm start' if entry.warm_start else ''})"
               if entry.epochs is not None else ""))


def round_entry(k: int, db: Path, card: ModelCard, cert: Certificate, seconds: float, **extra: Any) -> Round:
    """The record of round ``k`` (0: the model as given) after its certificate ``cert``: the
    samples (``extra`` gives ``samples_added`` and what else the round knows), the certificate's
    figures, the tests the ANN could not follow (``not_followed``) and how far it followed them
    (``followed``: the fractions of their increments, summed), the database's size in MB
    (``database_mb``, and ``database_raw_mb`` uncompressed) and the training (``training_record``)."""
    file_bytes, raw_bytes = database.sizes(db)
    lost = [t for t in cert.tests if not math.isfinite(t.figure)]
    return Round(round=k, **extra, samples_total=_n_samples(db), worst=cert.worst, worst_test=cert.worst_test,
                 passed=cert.passed, verdict=cert.verdict, seconds=seconds, not_followed=[t.name for t in lost],
                 followed=float(sum((t.departure or 0) / t.n_increments for t in lost if t.n_increments)),
                 database_mb=file_bytes / 1e6, database_raw_mb=raw_bytes / 1e6, **training_record(card))


def better(new: Round, kept: Round) -> bool:
    """Whether round ``new``'s certificate beats that of the model kept (``kept``), the rule that
    accepts a round: fewer tests the ANN cannot follow; or as many (some), followed further; or
    every test followed and a lower worst. A tie is no gain (the kept model stays)."""
    (n_new, f_new, w_new), (n_kept, f_kept, w_kept) = progress(new), progress(kept)
    if n_new != n_kept:
        return n_new < n_kept
    return f_new > f_kept if n_new else w_new < w_kept


def kept_round(rounds: Sequence[Round]) -> Round:
    """The round whose model the loop keeps: the last one not rejected (round 0, the model as
    given, is kept; a record without ``accepted`` reads as accepted)."""
    return [r for r in rounds if r.accepted is not False][-1]


def restarts(rounds: Sequence[Round]) -> int:
    """Rejected rounds so far [-]: each makes the next round restart its training with another seed."""
    return sum(r.accepted is False for r in rounds)


def rules_line(rounds: Sequence[Round]) -> str:
    """One line: how often the round rule fired (rounds run, accepted, rejected, restarts) and the round kept."""
    run = rounds[1:]
    restarted = sum(before.accepted is False for before in rounds[:-1])
    kept = kept_round(rounds)
    return (f"round rule: {len(run)} round(s) trained, {len(run) - restarts(run)} accepted, "
            f"{restarts(run)} rejected (no better than the model kept), {restarted} restarted with another "
            f"training seed; kept: round {kept.round} ({_figure(kept)})")


def candidate_path(model: Path) -> Path:
    """Where a round trains its model before it is judged (``<stem>_candidate.pt`` beside ``model``)."""
    model = Path(model)
    return model.with_name(f"{model.stem}_candidate{model.suffix}")


def model_files(model: Path) -> list[Path]:
    """The files ``training.fitting.train_and_save`` writes for ``model``: the weights, the JSON,
    the learning curve and the out-of-distribution index."""
    model = Path(model)
    return [model, model.with_suffix(".json"), model.with_name(f"{model.stem}_learning_curve.png"),
            model.with_name(f"{model.stem}_ood.npz")]


def _promotion_marker(model: Path) -> Path:
    """The file whose presence says that the candidate's files are being moved onto ``model``'s."""
    return candidate_path(model).with_suffix(".promoting")


def _promote(candidate: Path, model: Path) -> None:
    """Move the files of ``candidate`` (``candidate_path(model)``, complete) onto those of ``model``: a marker
    first, then each file by an atomic rename, the JSON last (``finish_promotion`` completes an interrupted one)."""
    _promotion_marker(model).touch()
    finish_promotion(model)


def finish_promotion(model: Path) -> bool:
    """Complete a promotion of the candidate onto ``model`` that an interruption left half done (its marker
    present): the candidate's files still there replace ``model``'s, so that the weights, the JSON and the
    out-of-distribution index are one model's again. Returns whether there was one to complete."""
    marker = _promotion_marker(model)
    if not marker.exists():
        return False
    pairs = list(zip(model_files(candidate_path(model)), model_files(model)))
    for source, target in pairs[2:] + pairs[:1] + pairs[1:2]:
        if source.exists():
            os.replace(source, target)
    marker.unlink()
    return True


def _discard(candidate: Path) -> None:
    for path in model_files(candidate):
        path.unlink(missing_ok=True)


@dataclasses.dataclass
class _Loop:
    """The state of ``learn`` between rounds: the kept model's card and certificate, the latest
    certificate and its DEM states (the DEM's states do not depend on the model) and the rounds."""

    card: ModelCard
    cert: Certificate
    states: dict[str, dict[str, np.ndarray]]
    rounds: list[Round]
    latest: Certificate
    progress: fitting.Progress | None = None
    """The trainings' progress callback (``learn``)."""


def _judge(k: int, db: Path, model: Path, config: TrainConfig, settings: ActiveSettings,
           measured: CertificateSettings, threads: int, loop: _Loop, t0: float, stored_entry: Mapping[str, Any],
           log: Callable[..., None]) -> None:
    """Round ``k`` after its samples were appended (``stored_entry``): train a candidate (a new
    seed after each rejected round, ``restarts``), certify it, keep it where it is ``better`` than
    the kept model, else discard it; record and log the round."""
    widths = tuple(stored_entry.get("hidden") or loop.card.architecture["hidden"])
    seed = config.seed + restarts(loop.rounds)
    candidate = candidate_path(model)
    cfg = dataclasses.replace(round_config(config, model, settings, widths), seed=seed)
    card = train_model(db, candidate, cfg, loop.rounds, progress=loop.progress, log=log)
    cert, loop.states = _certify(candidate, card, measured, settings, threads)
    loop.latest = cert
    capped = stored_entry.get("samples_capped")
    entry = round_entry(k, db, card, cert, time.perf_counter() - t0, samples_added=int(stored_entry["samples"]),
                        samples_capped=capped, tests=stored_entry.get("tests"),
                        departures=stored_entry.get("departures"), train_seed=seed)
    kept = kept_round(loop.rounds)
    entry = dataclasses.replace(entry, accepted=better(entry, kept))
    loop.rounds.append(entry)
    if entry.accepted:
        _promote(candidate, model)
        loop.card, loop.cert = card, cert
        log(round_line(entry) + ", ACCEPTED")
    else:
        _discard(candidate)
        log(round_line(entry) + f", REJECTED: no better than round {kept.round} ({_figure(kept)}), whose model "
            f"stays; the next round restarts its training with seed {config.seed + restarts(loop.rounds)}")
    loop.card = _record(model, loop.card, loop.rounds, loop.cert)


def _done(cert: Certificate | None, model: Path, db: Path, measured: CertificateSettings, settings: ActiveSettings,
          rounds: Sequence[Round], stored: Sequence[Mapping[str, Any]], dim: int) -> bool:
    """Whether a run recorded in the model's JSON already finished (nothing left to do on resume)."""
    return (_current(cert, model, measured, dim) and bool(rounds) and rounds[-1].round == len(stored)
            and (not short_of_aim(cert, settings) or len(stored) >= settings.rounds
                 or sum(r["samples"] for r in stored) >= settings.max_samples or stalled(rounds, settings)
                 or unresolvable_line(cert, aim(cert, settings)) is not None
                 or budget_room(db, settings.max_database_mb)[0] < min(settings.samples_per_round, MIN_ROUND_SAMPLES)))


def _stop_line(k: int, loop: _Loop, db: Path, settings: ActiveSettings, added_total: int, elapsed: float
               ) -> str | None:
    """Why round ``k`` does not start (one line), or None: budget spent, rounds stalled, or no round can help."""
    asked = min(settings.samples_per_round, settings.max_samples - added_total)
    if k > settings.rounds or asked <= 0 or elapsed > settings.max_seconds:
        return (f"active learning stops: budget spent (rounds {k - 1}/{settings.rounds}, samples "
                f"{added_total}/{settings.max_samples}, {elapsed:.0f}/{settings.max_seconds:g} s)")
    if stalled(loop.rounds, settings):
        return stall_line(loop.rounds, loop.latest, db, settings.departure_margin)
    return unresolvable_line(loop.cert, aim(loop.cert, settings))


def learn(db: Path, model: Path, config: TrainConfig, *, settings: ActiveSettings = ActiveSettings(),
          certify_settings: CertificateSettings = CertificateSettings(), seed: int = 0, threads: int = 1,
          card: ModelCard | None = None, log: Callable[..., None] = print, progress: fitting.Progress | None = None
          ) -> tuple[list[Round], Certificate]:
    """Certify ``model`` (trained on ``db``) and run rounds (module docstring) until it passes or
    the loop stops (budget, ``stall_line``, ``unresolvable_line``). A round's candidate replaces
    the kept model only where it is ``better`` (``_judge``), so the kept worst never rises.
    Returns the rounds (round 0: the model as given) and the kept model's certificate, both also
    in the model's JSON.

    Args:
        db: the model's database; the rounds append to it (``append_samples``).
        model: the ``.pt`` (its JSON beside it), replaced by each accepted round's model.
        config: the training settings; each round sets its widths, start and seed.
        certify_settings: what each round's certificate measures.
        seed: seed of the rounds' probes.
        threads: DEM and ANN threads.
        card: ``model``'s JSON already read (``training.card.read_card``); None: read here.
        log: receives one line per round and the trainings' summary lines.
        progress: receives every training's epochs (``training.fitting.Progress``; None: silent).
    """
    start = time.perf_counter()
    finished = finish_promotion(model)  # a round's files moved in half before an interruption: the card changes
    card = read_card(model) if card is None or finished else card
    stored = json.loads(str(_attrs(db).get("active_learning", "[]")))
    stored_cert, rounds = learning_of(card)
    rounds = [r for r in rounds if r.round <= len(stored)]
    spent = sum(r.seconds for r in rounds)  # by earlier processes of this run: --max-seconds counts them too
    dim = from_description(card.mesostructure).dim
    if not rounds and card.training_data["sha256"] != file_sha256(db):  # not trained on this database
        widths = tuple((stored[-1].get("hidden") if stored else None) or card.architecture["hidden"])
        card = train_model(db, model, round_config(config, model, settings, widths), rounds, progress=progress, log=log)
    elif _done(stored_cert, model, db, certify_settings, settings, rounds, stored, dim):
        log(round_line(rounds[-1]) + " (done before)")
        return rounds, stored_cert
    t0 = time.perf_counter()
    cert, states = _certify(model, card, certify_settings, settings, threads)
    if not rounds:
        rounds.append(dataclasses.replace(round_entry(
            len(stored), db, card, cert, time.perf_counter() - t0, samples_added=stored[-1]["samples"] if stored else 0,
            **({"tests": stored[-1].get("tests", [])} if stored else {})), accepted=True, train_seed=config.seed))
        log(round_line(rounds[-1]))
    loop = _Loop(_record(model, card, rounds, cert), cert, states, rounds, cert, progress)
    if rounds[-1].round < len(stored):  # appended before an interruption, not yet trained and judged
        _judge(len(stored), db, model, config, settings, certify_settings, threads, loop, time.perf_counter(),
               stored[-1], log)
    meso = from_description(str(_attrs(db)["mesostructure"]))
    added_total = sum(r["samples"] for r in stored)
    while short_of_aim(loop.cert, settings):
        k = len(stored) + 1
        stop = _stop_line(k, loop, db, settings, added_total, spent + time.perf_counter() - start)
        if stop is not None:
            log(stop)
            break
        t0 = time.perf_counter()
        picked, names = failing_states(loop.cert, loop.states, settings.departure_margin, aim(loop.cert, settings))
        if not names:
            log("active learning stops: the failing tests left no DEM states (the DEM did not run them)")
            break
        asked = min(settings.samples_per_round, settings.max_samples - added_total)
        room, per_sample = budget_room(db, settings.max_database_mb, sum(v.nbytes for v in picked.values()))
        n = min(asked, room)
        if n < min(asked, MIN_ROUND_SAMPLES):
            log(f"active learning stops: the database budget is spent ({db} {_mb(db):.1f} MB of "
                f"{settings.max_database_mb:g} MB at {per_sample / 1e3:.2f} kB per sample: {room} more samples fit, "
                f"round {k} asks {asked})")
            break
        samples = probe_states(meso, picked, n, round_seed(seed, k), _attrs(db), threads)
        widths = next_widths(loop.rounds, loop.card) if settings.widen else _architecture(loop.card)[0]
        departures = {t.name: [t.departure, t.n_increments] for t in loop.cert.tests
                      if t.name in names and t.departure is not None}
        entry = append_samples(db, samples, picked, {"tests": names, "seed": round_seed(seed, k),
                                                     "hidden": list(widths), "departures": departures,
                                                     "samples_capped": asked - n})
        stored.append(entry)
        added_total += entry["samples"]
        _judge(k, db, model, config, settings, certify_settings, threads, loop, t0, entry, log)
    log(rules_line(loop.rounds))
    return loop.rounds, loop.cert


def round_config(config: TrainConfig, model: Path, settings: ActiveSettings, widths: Sequence[int]) -> TrainConfig:
    """The training settings of a round: ``config`` with its hidden ``widths`` and, with a warm
    start, the model itself as the start weights (``init_from``)."""
    return dataclasses.replace(config, hidden=tuple(int(w) for w in widths),
                               **({"init_from": str(model)} if settings.warm_start else {}))


def _architecture(card: ModelCard) -> tuple[tuple[int, ...], int, int]:
    """(hidden widths, inputs, outputs) of the model of ``card``."""
    arch = card.architecture
    n_free = int(arch["n_free"])
    n_in = n_features(n_free, sum(arch["active_pairs"]), bool(arch.get("load_features", False)))
    return tuple(arch["hidden"]), n_in, n_free + n_free**2


def multiply_adds(widths: Sequence[int], n_in: int, n_out: int) -> int:
    """Multiply-adds of one cell through a perceptron of hidden ``widths`` [-] (its cost per cell-step)."""
    sizes = (n_in, *widths, n_out)
    return sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))


def next_widths(rounds: Sequence[Round], card: ModelCard) -> tuple[int, ...]:
    """Hidden widths of the next round's network: the model's (``card``), or, where the last round's
    certificate worst fell by less than ``WIDEN_BELOW_GAIN`` from the round before it (two
    rounds known), the first rung of ``WIDTH_LADDER`` that costs more multiply-adds than
    the model's network (none left: the model's)."""
    widths, n_in, n_out = _architecture(card)
    if len(rounds) < 2 or rounds[-1].worst * WIDEN_BELOW_GAIN <= rounds[-2].worst:
        return widths
    cost = multiply_adds(widths, n_in, n_out)
    return next((rung for rung in WIDTH_LADDER if multiply_adds(rung, n_in, n_out) > cost), widths)


def training_record(card: ModelCard) -> dict[str, Any]:
    """What a round stores of its training (the model's ``card``): ``hidden`` widths, ``epochs`` run,
    ``train_seconds``, ``warm_start`` (whether it started from the previous weights; None: not asked)."""
    warm = card.history.get("warm_start")
    return {"hidden": list(card.architecture["hidden"]), "epochs": card.history["epochs_run"],
            "train_seconds": card.history["seconds"], "warm_start": None if warm is None else bool(warm["used"])}


def train_model(db: Path, model: Path, config: TrainConfig, rounds: list[Round], *,
                progress: fitting.Progress | None = None, log: Callable[..., None] | None = None) -> ModelCard:
    """Train ``model`` on ``db`` from scratch (``training.fitting.train_and_save``, settings
    ``config``, the model overwritten; ``progress`` receives its epochs, ``log`` its summary lines,
    None: silent); its JSON keeps the ``rounds`` so far (an interrupted loop resumes with them).
    Returns the new model's card."""
    fitting.train_and_save(db, model, config, overwrite=True, progress=progress, **({"log": log} if log else {}))
    return write_rounds(model, read_card(model), rounds)


def write_rounds(model: Path, card: ModelCard, rounds: Sequence[Round]) -> ModelCard:
    """``card`` with ``rounds`` under ``active_learning``, written as ``model``'s JSON (atomically); returns it."""
    card = dataclasses.replace(card, active_learning=[r.to_dict() for r in rounds])
    write_card(model, card)
    return card


def _attrs(db: Path) -> dict[str, Any]:
    with h5py.File(db, "r") as f:
        return dict(f.attrs)


def _n_samples(db: Path) -> int:
    with h5py.File(db, "r") as f:
        return int(f["d_eps"].shape[0])
