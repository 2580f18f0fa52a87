"""The settings of the learning loop, apart from the loop itself: the certificate's
(``CertificateSettings``, measured by ``homogenization.learning.certificate.certify``) and the budget and
sampling of the active-learning rounds (``ActiveSettings``, run by ``homogenization.learning.active``);
the single home of their defaults.

Light on purpose: the commands read these defaults for their flags (``hmodel certify``, ``hmodel
train``, ``hmodel learn``, ``homogenization.cli.options.add_active_arguments``) without
importing torch or Warp.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from homogenization.ann.envelope import has_fine_grains, MINIMUM

FINES_EQUILIBRIUM_CORRECTIONS = 20
"""Default equilibrium corrections K of the certificate, and so of the runs, of a spatial cell with
fine grains (``default_equilibrium``) [-]: a cap, reached only in cells whose Newton steps do not
converge (counted as unconverged); K = 2 stopped a drained test that K = 5 followed, and on a cell
nobody tuned for K = 20 followed a drained test that K = 5 did not (docs/certificate.md, "The
default pipeline of a 3D cell with fine grains")."""
FINES_EQUILIBRIUM_TOLERANCE = 1e-4
"""Default force ratio above which such a cell is corrected [-]. A cell whose force ratio crosses
the tolerance from one trial to the next jumps by the correction, about the tolerance times its
largest force: at 1e-3 these jumps stopped the stress control of drained tests of two cells
nobody tuned for, at 1e-4 to 1e-6 the same model followed them within 0.021 % of the scale of the
DEM (docs/certificate.md, "The default pipeline of a 3D cell with fine grains"); undrained, 1e-4
is within 0.005 % while the network's guess still decides 19-37 % of the cell-increments (docs/ann.md,
"Equilibrium corrections"; the DEM's 1e-6 corrects 90-99 % of them)."""


RELEASE_RULE_NAMES = ("resting", "drag")
"""Names of the hybrid's released-grain rules that a certificate can measure (``--release-rule``):
``homogenization.ann.escalation.RELEASE_RULE`` (the default) and ``RELEASE_RULE_DRAG``."""


def release_rule_text(name: str) -> str:
    """The rule ``name`` (``RELEASE_RULE_NAMES``) as ``homogenization.ann.escalation`` words it (and certificates
    record it)."""
    from homogenization.ann.escalation import RELEASE_RULE, RELEASE_RULE_DRAG  # noqa: PLC0415 (light module)

    return {"resting": RELEASE_RULE, "drag": RELEASE_RULE_DRAG}[name]


def default_equilibrium(meso: Any) -> tuple[int, float | None]:
    """(K, tolerance) of the surrogate that ``hmodel train``, ``learn`` and ``certify`` certify by
    default for cells of ``meso``: (``FINES_EQUILIBRIUM_CORRECTIONS``,
    ``FINES_EQUILIBRIUM_TOLERANCE``) for a spatial cell with fine grains (``has_fine_grains``),
    where the network alone misses the DEM by 30-49 % (docs/ann.md), else (0, None), the network
    alone (planar cells, the plain ten-sphere cell)."""
    if int(meso.dim) == 3 and has_fine_grains(meso):
        return FINES_EQUILIBRIUM_CORRECTIONS, FINES_EQUILIBRIUM_TOLERANCE
    return 0, None


@dataclass(frozen=True)
class CertificateSettings:
    """What a certificate measures (``homogenization.learning.certificate.certify``); the defaults are the
    minimum certificate (``homogenization.ann.envelope.MINIMUM``)."""

    pressures: tuple[float, ...] = MINIMUM.pressures
    """Confining pressures p0 of the tests [N/m in 2D, Pa in 3D]."""
    eps_max: float = MINIMUM.eps_max
    """Axial strain of each shear stage, counted from its start [-]."""
    increment: float = MINIMUM.increment
    """Strain increment of every stage [-]."""
    n_orientations: int = MINIMUM.n_orientations
    """Cell orientations of every test of a planar cell [-]."""
    spatial_rule: tuple[int, int] = MINIMUM.spatial_rule
    """(Lebedev order, spins) of every test of a spatial cell."""
    target: float = MINIMUM.target
    """Largest dp or dq allowed, as a fraction of max(p0, largest DEM p) [-]."""
    rollout: bool = True
    """Also run the single-cell rollouts (reported, not part of the verdict)."""
    equilibrium_corrections: int = 0
    """Exact Newton steps on the free grains' balance after the network's step in the tests' ANN runs
    (``AnnCell(equilibrium_corrections=...)``, spatial cells) [-]; 0: the network alone."""
    equilibrium_tolerance: float | None = None
    """Force ratio above which a cell is corrected [-] (None: the DEM's ``force_tolerance``); only with
    ``equilibrium_corrections`` > 0."""
    release_rule: str = "resting"
    """The hybrid's rule for the free grains nothing presses, by name (``RELEASE_RULE_NAMES``): ``"resting"``
    (``homogenization.ann.escalation.RELEASE_RULE``) or ``"drag"`` (``RELEASE_RULE_DRAG``, with
    ``equilibrium_corrections`` > 0 only)."""

    def __post_init__(self) -> None:
        if self.release_rule not in RELEASE_RULE_NAMES:
            raise ValueError(f"release_rule = {self.release_rule!r}: one of {', '.join(RELEASE_RULE_NAMES)}")
        if self.release_rule != RELEASE_RULE_NAMES[0] and not self.equilibrium_corrections:
            raise ValueError(f"release rule {self.release_rule!r}: a rule of the hybrid, and these tests run the "
                             f"network alone (equilibrium corrections 0, or a cell without fine grains)")
        if int(self.equilibrium_corrections) < 0:
            raise ValueError(f"equilibrium_corrections = {self.equilibrium_corrections} must be >= 0")
        if self.equilibrium_tolerance is not None:
            if not self.equilibrium_corrections:
                raise ValueError("equilibrium_tolerance applies with equilibrium_corrections > 0 only")
            if not self.equilibrium_tolerance > 0.0:
                raise ValueError(f"equilibrium_tolerance = {self.equilibrium_tolerance:g} must be > 0")

    def keywords(self) -> dict[str, Any]:
        """The settings as keywords of ``homogenization.learning.certificate.certify`` (the release rule as
        ``homogenization.ann.escalation`` words it)."""
        words = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        words["release_rule"] = release_rule_text(self.release_rule)
        return words


@dataclass(frozen=True)
class ActiveSettings:
    """Budget and sampling of the active-learning loop (the single home of their defaults)."""

    rounds: int = 3
    """Rounds at most (each: probe, append, retrain, certify) [-]."""
    samples_per_round: int = 20_000
    """Samples added per round [-] (spread evenly over the states of the failing tests)."""
    max_samples: int = 100_000
    """Samples added over all rounds at most [-]."""
    max_seconds: float = 4 * 3600.0
    """Wall time [s] after which no new round starts; a resumed run counts its earlier processes' rounds too."""
    state_every: int = 10
    """Increments between two DEM states kept along a certificate test [-]."""
    warm_start: bool = False
    """Retrain each round from the previous round's weights (``training.train --init-from``)
    instead of random weights (docs/certificate.md, "Warm start": measured no better)."""
    widen: bool = True
    """Let a round train a wider network (``homogenization.learning.active.next_widths``: the next rung of ``WIDTH_LADDER``)
    when the round before it gained less than ``homogenization.learning.active.WIDEN_BELOW_GAIN``."""
    departure_margin: float = 1.0
    """Of a failing test, the DEM states from its point of departure (the increment that first put
    the ANN more than the target off the DEM, or that the ANN could not follow) back by this
    fraction of the test's increments, and every state after it, are probed [-]; 1 (the default):
    every state of the test (docs/certificate.md, "The pipeline of a 3D cell with a fine grain":
    in the one comparison made, 0.1 left round 1 at 2.19 % where every state gave 0.99 %)."""
    stall_rounds: int = 2
    """Rounds in a row without progress on the best round so far (``homogenization.learning.active.improved``)
    after which the loop stops with a one-line diagnosis [-]."""
    max_database_mb: float = 300.0
    """Size budget of the database file [MB, 1e6 bytes]: a round adds only the samples that fit
    (at the file's own bytes per sample) and none once it is spent."""
    round_target: float | None = None
    """Worst figure the rounds aim at [-]: they go on while the kept certificate fails or, passed, is
    worst above this fraction of its scale (a stricter aim than the certificate's target; the verdict is
    still the target's). None: the certificate's target."""

    def __post_init__(self) -> None:
        for name in ("rounds", "samples_per_round", "max_samples", "state_every", "stall_rounds"):
            least = 0 if name == "rounds" else 1
            if int(getattr(self, name)) < least:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= {least}")
        for name in ("max_seconds", "max_database_mb"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} = {getattr(self, name):g} must be > 0")
        if self.round_target is not None and not self.round_target > 0.0:
            raise ValueError(f"round_target = {self.round_target:g} must be > 0")
        if not 0.0 <= self.departure_margin <= 1.0:
            raise ValueError(f"departure_margin = {self.departure_margin:g} must lie in [0, 1]")
