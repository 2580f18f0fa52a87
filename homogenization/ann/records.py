"""The records of the learning loop as the model's JSON stores them: ``Certificate`` and its ``TestResult`` rows, ``Round``.

Part of the model card's file format: its ``format_version`` (``training.checkpoint.FORMAT_VERSION``)
versions them too, so a record carries no version key of its own. ``to_dict`` gives back the
mapping ``from_dict`` read, key for key (an optional entry absent stays absent), so that a file
read and written again is the same bytes (``json.dumps(indent=2, sort_keys=True)``).

Sign convention: compression and contraction positive; stresses in N/m (planar) or Pa (spatial).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Sequence

from training.record_io import record_dict, record_keywords

if TYPE_CHECKING:  # training.card imports torch (through the checkpoint): not for commands' --help
    from training.card import ModelCard


@dataclass(frozen=True)
class TestResult:
    """One homogenised test of a certificate: the ANN against the DEM."""

    __test__: ClassVar[bool] = False  # not a pytest class
    OPTIONAL: ClassVar[frozenset[str]] = frozenset({"error", "departure", "stress_control_jumps", "dem_spread",
                                                    "dem_spread_error"})
    """Keys a test records only where they arise (None: absent)."""

    name: str
    """E.g. "drained compression p0=200000"."""
    kind: str
    """"constant-volume", "drained" (planar) or "undrained", "drained" (spatial)."""
    sense: str
    """"compression", "extension" or "reversal"."""
    p0: float
    """Confining pressure [N/m or Pa]."""
    dp: float
    """max abs(p_ann - p_dem) / scale over the shear stages [-]; inf where the ANN could not follow."""
    dq: float
    """Likewise for q [-]."""
    scale: float
    """max(p0, largest DEM p of the test) [N/m or Pa]."""
    n_increments: int
    """The test's length [-]."""
    error: str | None = None
    """Why the ANN could not follow the programme."""
    departure: int | None = None
    """The increment that put the ANN more than the target off the DEM (or that it could not follow)."""
    stress_control_jumps: dict[str, int] | None = None
    """Increments accepted across a jump of the response: {"ann": n, "dem": n}."""
    dem_spread: float | None = None
    """The DEM from rest against the DEM [-] (inf where it could not follow)."""
    dem_spread_error: str | None = None
    """Why the DEM from rest could not follow the programme."""

    @property
    def figure(self) -> float:
        """max(dp, dq) [-]."""
        return max(self.dp, self.dq)

    def to_dict(self) -> dict[str, Any]:
        """The row as the model's JSON stores it."""
        return record_dict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "TestResult":
        """The row of its ``to_dict`` (ValueError, one line, for an unknown or missing key)."""
        return cls(**record_keywords(cls, values))


@dataclass(frozen=True)
class Certificate:
    """The certificate of a meso-ANN model (``homogenization.learning.certificate.certify``, docs/certificate.md)."""

    OPTIONAL: ClassVar[frozenset[str]] = frozenset({"envelope", "equilibrium", "command"})
    """Keys recorded only where they arise (None: absent)."""

    target: float
    """Largest dp or dq allowed [-]."""
    worst: float
    """The largest dp or dq of the tests [-]."""
    worst_test: str
    """The name of that test."""
    metric: str
    """What dp and dq measure, in words."""
    tests: tuple[TestResult, ...]
    """The tests, in the order run."""
    rollout: dict[str, Any] | None
    """The single-cell rollouts (``training.rollout.rollout_report``; reported only); None: not run."""
    coverage: dict[str, Any] | None
    """``fraction_within``, ``n_states``, ``threshold``, ``every_increments``; None without an index."""
    dem_spread: dict[str, Any] | None
    """The DEM's reproducibility: ``max``, ``test``, ``above_target``; None: not measured."""
    settings: dict[str, Any]
    """What was measured (``certificate.requested_settings``, with ``mesostructure`` and ``n_cells``)."""
    cell_parameters: dict[str, float]
    """The cell's parameters, e.g. alpha0_deg."""
    model_sha256: str
    """sha256 of the ``.pt`` certified."""
    revision: str
    """git revision of the code that measured it (``-dirty`` where the tree differed)."""
    seconds: float
    """Time taken [s]."""
    within_target: bool
    """worst <= target."""
    below_minimum: list[str]
    """Where the settings are weaker than the minimum certificate (``envelope.shortfalls``)."""
    verdict: str
    """"passed", "failed" or "weak" (``envelope.verdict``)."""
    passed: bool
    """verdict == "passed"."""
    envelope: dict[str, Any] | None = None
    """What the tests covered (``envelope.envelope_of``)."""
    equilibrium: dict[str, Any] | None = None
    """How often the hybrid's equilibrium corrections fired (``certify(equilibrium_corrections=K)``)."""
    command: str | None = None
    """The command line that measured it (``hmodel certify``)."""

    def to_dict(self) -> dict[str, Any]:
        """The certificate as the model's JSON stores it under ``"certificate"``."""
        return {**record_dict(self), "tests": [t.to_dict() for t in self.tests]}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "Certificate":
        """The certificate of its ``to_dict`` (ValueError, one line, for an unknown or missing key)."""
        fields = record_keywords(cls, values)
        return cls(**{**fields, "tests": tuple(TestResult.from_dict(t) for t in fields["tests"])})

    def test(self, name: str) -> TestResult:
        """The test called ``name`` (StopIteration where none is)."""
        return next(t for t in self.tests if t.name == name)


@dataclass(frozen=True)
class Round:
    """One active-learning round as the model's JSON stores it under ``"active_learning"``
    (``homogenization.learning.active.round_entry``; round 0: the model as given).

    The training's figures (``hidden``, ``epochs``, ``train_seconds``, ``warm_start``) are written
    together where the round records its training (``epochs`` not None), ``warm_start`` as null
    where the training was not asked to start warm.
    """

    OPTIONAL: ClassVar[frozenset[str]] = frozenset({
        "verdict", "not_followed", "followed", "database_mb", "database_raw_mb", "samples_capped", "tests",
        "departures", "hidden", "epochs", "train_seconds", "warm_start", "accepted", "train_seed"})
    """Keys recorded only where they arise (None: absent), ``warm_start`` apart (see above)."""

    round: int
    """The round's index [-] (0: the model as given)."""
    samples_added: int
    """Samples the round appended to the database [-]."""
    samples_total: int
    """The database's samples after it [-]."""
    worst: float
    """Its certificate's worst [-] (inf: a test the ANN could not follow)."""
    worst_test: str
    """The name of that test."""
    passed: bool
    """Its certificate passed."""
    seconds: float
    """Time the round took (probes, training, certificate) [s]."""
    verdict: str | None = None
    """Its certificate's verdict ("passed", "failed", "weak")."""
    not_followed: list[str] | None = None
    """The tests the ANN could not follow."""
    followed: float | None = None
    """The fractions of those tests' increments it followed, summed [-]."""
    database_mb: float | None = None
    """The database's size on disk after the round [MB]."""
    database_raw_mb: float | None = None
    """Likewise, uncompressed [MB]."""
    samples_capped: int | None = None
    """Samples the round left out for the database's size budget [-]."""
    tests: list[str] | None = None
    """The failing tests whose DEM states it probed."""
    departures: dict[str, list[int]] | None = None
    """Of those tests: [departure increment, increments] [-]."""
    hidden: list[int] | None = None
    """Hidden widths of the network it trained [-]."""
    epochs: int | None = None
    """Epochs the training ran [-]."""
    train_seconds: float | None = None
    """Time the training took [s]."""
    warm_start: bool | None = None
    """Whether the training started from the previous weights (None: not asked)."""
    accepted: bool | None = None
    """Whether its model beat the model kept before it and replaced it (False: rejected, the kept
    model stays; None: recorded before rounds were judged, read as accepted)."""
    train_seed: int | None = None
    """Seed of its training [-] (a round after a rejected one restarts with another)."""

    def to_dict(self) -> dict[str, Any]:
        """The round as the model's JSON stores it."""
        return {**record_dict(self), **({"warm_start": self.warm_start} if self.epochs is not None else {})}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "Round":
        """The round of its ``to_dict`` (ValueError, one line, for an unknown or missing key)."""
        return cls(**record_keywords(cls, values))


def certificate_of(metadata: Mapping[str, Any]) -> Certificate | None:
    """The certificate a model's JSON ``metadata`` records under ``"certificate"`` (None: uncertified)."""
    values = metadata.get("certificate")
    return None if values is None else Certificate.from_dict(values)


def learning_of(card: ModelCard) -> tuple[Certificate | None, list[Round]]:
    """The certificate (None: uncertified) and the active-learning rounds ([]: none) of a model's ``card``."""
    return certificate_of(card.to_dict()), [Round.from_dict(r) for r in card.active_learning or []]


def with_learning(card: ModelCard, cert: Certificate, rounds: Sequence[Round]) -> ModelCard:
    """``card`` recording ``cert`` and ``rounds`` (the model's JSON as the learning loop writes it)."""
    return dataclasses.replace(card, certificate=cert.to_dict(), active_learning=[r.to_dict() for r in rounds])
