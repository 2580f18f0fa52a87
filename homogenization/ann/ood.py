"""Out-of-distribution checks of a meso-ANN cell's start states against its model's index (``training.ood``).

With the index file beside the model (``training.ood.index_path``), every ``interval``-th distinct
start state of the cell's ``step`` is checked: its cells' z-scored state features are compared with
the indexed database states. A step's diagnostics then hold ``n_ood_checked`` (cells checked at this
increment: n_cells or 0) and ``n_ood`` (those beyond the index's threshold). Once the cumulative
fraction exceeds ``training.ood.WARN_FRACTION`` one ``RuntimeWarning`` says so (again in a run resumed
from a checkpoint past it: ``resumed``). Without an index file
the two counts are absent and ``index`` is None.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from training.ood import index_path, load_index, OodError, OodIndex, state_features, WARN_FRACTION

OOD_INTERVAL = 500
"""Distinct start states of ``AnnCell.step`` between two out-of-distribution checks: one check
of 360 cells costs ~0.8-1.8 ms, so every 500th increment adds ~2-4 us to a ~80 us step
(docs/certificate.md)."""


class OodMonitor:
    """The out-of-distribution checks of one cell model.

    Args:
        net: the model's ``training.fast_model.NetArrays`` (its normalisation names the index it reads), or
            its ``MesoNet`` (which also computes the features ``diagnostics`` is not given).
        path: the model file; the index is read from beside it (a corrupt index: a ``RuntimeWarning``, no checks).
        interval: distinct start states between two checks, >= 1 (ValueError otherwise).

    Attributes:
        index: the ``OodIndex``, None without one.
        counts: cumulative (cells beyond the threshold, cells checked) over this object's checks.
    """

    def __init__(self, net: Any, path: Path, interval: int = OOD_INTERVAL) -> None:
        if int(interval) < 1:
            raise ValueError(f"ood_interval = {interval} must be >= 1")
        self.net = net
        self.path = path
        self.interval = int(interval)
        self.index: OodIndex | None = None
        ood_file = index_path(path)
        if ood_file.is_file():
            try:
                self.index = load_index(ood_file, net)
            except OodError as exc:
                warnings.warn(f"ann: {exc}; out-of-distribution checks are off", RuntimeWarning, stacklevel=3)
        self.counts = np.zeros(2, dtype=np.int64)
        self._last_state: object = None
        self._states = 0
        self._result: tuple[float, float] | None = None
        self._warned = False

    def due(self, state: Any) -> bool | None:
        """None without an index; else whether to check this call's start state: every
        ``interval``-th distinct one, once (trials from the same state reuse its counts)."""
        if self.index is None:
            return None
        if state is not self._last_state:
            self._last_state = state
            self._states += 1
            self._result = None
        return self._result is None and (self._states - 1) % self.interval == 0

    def _check(self, state: Any, features: np.ndarray | None) -> tuple[float, float]:
        """(n_ood, n_checked) of the cells of ``state``; ``features``: their z-scored state
        features (n, n_state_features), or None to compute them."""
        if features is None:
            features = state_features(self.net, *state)
        n_out = int(np.count_nonzero(self.index.outside(features)))
        self.counts += (n_out, features.shape[0])
        if not self._warned and self.counts[0] > WARN_FRACTION * self.counts[1]:
            self._warned = True
            self._warn(stacklevel=5)
        return float(n_out), float(features.shape[0])

    def _warn(self, stacklevel: int) -> None:
        warnings.warn(f"ann: {self.counts[0]} of {self.counts[1]} checked cell-increments lie beyond the "
                      f"out-of-distribution threshold of {self.path.name} (> {WARN_FRACTION:.0%}): the "
                      f"network extrapolates (diagnostics n_ood, n_ood_checked)", RuntimeWarning, stacklevel=stacklevel)

    def resumed(self) -> None:
        """After the counts of an interrupted run were restored (a checkpoint): its warning again, where it was said."""
        if self._warned:
            self._warn(stacklevel=3)

    def diagnostics(self, due: bool | None, state: Any, features: np.ndarray | None) -> dict[str, float]:
        """``n_ood``, ``n_ood_checked`` of this call (zeros where its state is not checked); {} without an index.
        ``due``: ``due(state)``'s answer; ``features``: the state's z-scored features, or None to compute them."""
        if due is None:
            return {}
        if due:
            self._result = self._check(state, features)
        n_out, n_checked = self._result or (0.0, 0.0)
        return {"n_ood": n_out, "n_ood_checked": n_checked}
