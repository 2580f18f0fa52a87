"""The budget and sampling of the active-learning rounds (``ActiveSettings``: the single home of
their defaults), apart from the rounds themselves (``homogenization.active``).

Light on purpose: the commands read these defaults for their flags (``hmodel train``, ``hmodel
learn``, ``homogenization.cli.options.add_active_arguments``) without importing torch or Warp.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    """Wall time [s] after which no new round starts."""
    state_every: int = 10
    """Increments between two DEM states kept along a certificate test [-]."""
    warm_start: bool = False
    """Retrain each round from the previous round's weights (``training.train --init-from``)
    instead of random weights (docs/certificate.md, "Warm start": measured no better)."""
    widen: bool = True
    """Let a round train a wider network (``homogenization.active.next_widths``: the next rung of ``WIDTH_LADDER``)
    when the round before it gained less than ``homogenization.active.WIDEN_BELOW_GAIN``."""

    def __post_init__(self) -> None:
        for name in ("rounds", "samples_per_round", "max_samples", "state_every"):
            least = 0 if name == "rounds" else 1
            if int(getattr(self, name)) < least:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= {least}")
        if not self.max_seconds > 0.0:
            raise ValueError(f"max_seconds = {self.max_seconds:g} must be > 0")
