"""A programme step as the engine runs it: per component strain or stress control, the targets of each
increment, the coupling to sigma11 and the stop on p.

``Plan.from_step(step, stress_start, n_voigt)`` resolves a ``homogenization.element_test.programme.Step`` of a
programme for n material points: the strain-controlled components advance by ``target /
n_increments`` per increment, the stress-controlled ones follow a ramp from their stress at the start
of the step to the target. ``Plan`` can also be written directly (a calibration's population):
``held`` stress targets (the same every increment, e.g. sigma22 = p0 of a drained test) and a first
guess of the stress-controlled increments.

Increments are Voigt rows (n, n_voigt) [-]; stresses [N/m] (2D) or [Pa] (3D); compression positive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from homogenization.element_test.programme import Step


@dataclass
class Plan:
    """How the increments of one stage are driven, for n material points.

    Attributes:
        label: stage label.
        n_increments: increments of the stage (an upper bound where it stops on p).
        increment: macro increment of every point, shape (n, n_voigt): the strain-controlled components
            and the first guess of the stress-controlled ones [-].
        idx: the stress-controlled components (indices into the normal components), shape (k,).
        start: stress-controlled components at the start of the stage, shape (n, k) (unused where ``held``).
        end: their targets at the end of the stage, shape (n, k) [N/m or Pa].
        held: targets are ``end`` at every increment instead of a ramp from ``start``.
        coupling: per stress component, d sigma_i / d sigma11 imposed (None: none), shape (3 or 6,).
        sigma11_start: sigma11 of every point at the start of the stage, shape (n,).
        stop_at_p: end the stage where p reaches this (None: run every increment).
    """

    label: str
    n_increments: int
    increment: np.ndarray
    idx: np.ndarray
    start: np.ndarray
    end: np.ndarray
    held: bool = False
    coupling: np.ndarray | None = None
    sigma11_start: np.ndarray | None = None
    stop_at_p: float | None = None

    @classmethod
    def from_step(cls, step: Step, stress: np.ndarray, n_voigt: int) -> Plan:
        """The plan of ``step`` from the stresses (n, 3 or 6) at its start (module docstring)."""
        n, dim = stress.shape[0], step.dim
        mask = np.array(step.stress_mask)
        idx = np.flatnonzero(mask)
        increment = np.zeros((n, n_voigt))
        increment[:, :dim] = np.where(mask, 0.0, np.asarray(step.target) / step.n_increments)
        end = np.broadcast_to(np.asarray(step.target)[idx], (n, idx.size))
        coupling = None
        if step.coupling is not None:
            coupling = np.zeros(stress.shape[1])
            coupling[:dim] = step.coupling
        return cls(step.label, step.n_increments, increment, idx, stress[:, idx].copy(), end, False, coupling,
                   stress[:, 0].copy(), step.stop_at_p)

    def target(self, i: int) -> np.ndarray:
        """Targets of the stress-controlled components at the end of increment ``i`` (0-based), shape (n, k)."""
        if self.held:
            return self.end
        return self.start + (self.end - self.start) * ((i + 1) / self.n_increments)

    def controlled(self, stress: np.ndarray) -> np.ndarray:
        """The stresses (n, k) that stress control sets to the targets: sigma[idx], less the coupling to sigma11."""
        if self.coupling is None:
            return stress[:, self.idx]
        return stress[:, self.idx] - self.coupling[self.idx] * (stress[:, :1] - self.sigma11_start[:, None])

    def controlled_tangent(self, tangent: np.ndarray) -> np.ndarray:
        """d(``controlled``)/d(d_e) of every stress component row from the material tangents (n, m, n_voigt)."""
        if self.coupling is None:
            return tangent
        return tangent - self.coupling[None, :, None] * tangent[:, :1, :]
