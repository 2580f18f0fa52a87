"""Exact equilibrium corrections of the meso-ANN's step in torch (float64): the network's guess, then Newton.

The torch counterpart of ``training.fast_equilibrium3d`` (same rule, same counts), for the paths
that run torch: another device, and the consistent tangent of a spatial cell by autograd. The
network's free-DOF displacement (``MesoNet.advance``'s) is the first guess, the DEM's rest rule
is applied to it (``cell_physics.hold_at_rest``), then up to ``iterations`` Newton steps on the
balance of the free DOFs, R(d) = net contact force on the free DOFs after the increment by the
exact contact law (``cell_physics.advance``), J = dR/dd by autograd (one backward pass per free
DOF, all cells at once), each step solving (J - REGULARISATION kn I) delta = -R, in the cells
whose force ratio max abs(R) / max f_n exceeds ``tolerance`` and whose probe is at least
``RELAXATION_RAMP``, globalised as the compiled steps are (the matrix shifted where the step does
no positive work along R, another step halved until the sum of squared residuals falls;
``training.fast_equilibrium3d``'s docstring) and counted the same way.

Derivative: where ``d_eps`` requires grad, the corrected displacement carries the derivative of the
equilibrium, -J^-1 dR/d(d_eps) at the last iterate (one more linearisation, whose value is added
and subtracted so that the displacement's value is the iterate's) in the cells that took a step; a
cell that took none (its guess within the tolerance, or its probe below the ramp) keeps the network's
displacement and its derivative: the tangent is the derivative of the step taken.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from training import cell_physics
from training.fast_equilibrium3d import HALVINGS, REGULARISATION, SHIFT
from training.network import features_and_contacts, MesoNet, RELAXATION_RAMP


class Corrected(NamedTuple):
    """Outcome of ``corrected_advance``: the increment (``cell_physics.Increment``), force_ratio (2, n)
    (first guess, after the corrections; 0 where not evaluated), corrections (n,) int64 (Newton steps),
    and of them shortened (n,) int64 (by the line search) and shifted (n,) int64 (the matrix shifted)."""

    increment: cell_physics.Increment
    force_ratio: torch.Tensor
    corrections: torch.Tensor
    shortened: torch.Tensor
    shifted: torch.Tensor


def balance(schema: cell_physics.CellSchema, cell_size, free_position, shear_force, d_eps, d_free,
            old: cell_physics.Contacts) -> tuple[torch.Tensor, torch.Tensor]:
    """Net contact force on the free DOFs after the increment [N], (n, n_free), and the largest normal
    force [N], (n,), for the free-DOF displacement d_free (n, n_free) [m] (no rest rule)."""
    inc = cell_physics.advance(schema, cell_size, free_position, shear_force, d_eps, d_free, old)
    x = cell_physics.positions(schema, inc.cell_size, inc.free_position)
    c = cell_physics.contacts(schema, x)
    force = cell_physics.pair_forces(c, inc.shear_force)
    return cell_physics.unbalanced(schema, force, x.shape[1]), c.normal_force.amax(dim=1)


def _jacobian(schema, state, d_eps, d_free, old) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """R (n, n_free), f_n max (n,) and J = dR/dd (n, n_free, n_free) at d_free, detached."""
    with torch.enable_grad():
        trial = d_free.detach().clone().requires_grad_(True)
        residual, fn_max = balance(schema, *state, d_eps.detach(), trial, old)
        rows = [torch.autograd.grad(residual[:, k].sum(), trial, retain_graph=k < residual.shape[1] - 1)[0]
                for k in range(residual.shape[1])]
    return residual.detach(), fn_max.detach(), torch.stack(rows, dim=1)


def _downhill(matrix: torch.Tensor, residual: torch.Tensor, first: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The Newton steps (m, n_free) [m] of the ``matrix`` (m, n_free, n_free) [N/m] and ``residual`` (m, n_free)
    [N] of the corrected cells, and whether each was shifted (m,): where a step does no positive work
    along the residual, the matrix plus lambda I, lambda = ``first`` [N/m] doubled until it does
    (``first`` = 0: never; ``training.fast_equilibrium3d``)."""
    delta = torch.linalg.solve(matrix, residual.unsqueeze(-1)).squeeze(-1)
    uphill = ~((residual * delta).sum(dim=1) > 0) if first > 0 else torch.zeros_like(residual[:, 0], dtype=torch.bool)
    shifted = uphill.clone()
    eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype, device=matrix.device)
    lam = torch.full_like(residual[:, 0], first)
    for _ in range(64):
        if not bool(uphill.any()):
            break
        trial = torch.linalg.solve(matrix[uphill] + lam[uphill, None, None] * eye, residual[uphill].unsqueeze(-1))
        delta[uphill] = trial.squeeze(-1)
        lam = torch.where(uphill, 2.0 * lam, lam)
        uphill = uphill & ~((residual * delta).sum(dim=1) > 0)
    return delta, shifted


def _line_search(schema, state, d_eps, d, delta, residual, active, full, halvings: int, old, shortened) -> torch.Tensor:
    """d + alpha delta (n, n_free) [m] in the ``active`` cells, d + delta in the ``full`` ones (shifted
    steps), d elsewhere: alpha the first of 1, 1/2, ..., 2^-halvings whose sum of squared residuals is
    below that of ``residual`` (at d), else 2^-halvings; counts the cells' steps taken at alpha < 1 in
    ``shortened`` (n,), in place."""
    with torch.no_grad():
        d = torch.where(full.unsqueeze(-1), d + delta, d)
        merit = (residual * residual).sum(dim=1)
        alpha = torch.ones_like(merit)
        pending = active.clone()
        for trial in range(int(halvings) + 1):
            if not bool(pending.any()):
                break
            trial_d = torch.where(pending.unsqueeze(-1), d + alpha.unsqueeze(-1) * delta, d)
            trial_residual, _ = balance(schema, *state, d_eps.detach(), trial_d, old)
            accept = pending & (((trial_residual * trial_residual).sum(dim=1) < merit) | (trial == int(halvings)))
            d = torch.where(accept.unsqueeze(-1), trial_d, d)
            if trial > 0:
                shortened += accept.to(shortened.dtype)
            pending = pending & ~accept
            alpha = torch.where(pending, 0.5 * alpha, alpha)
    return d


def corrected_advance(net: MesoNet, cell_size, free_position, shear_force, d_eps, iterations: int,
                      tolerance: float, halvings: int = HALVINGS, shift: float = SHIFT,
                      regularisation: float = REGULARISATION) -> Corrected:
    """``MesoNet.advance`` with up to ``iterations`` exact Newton corrections (module docstring);
    ``regularisation`` [-] the diagonal stiffness added to -J as a fraction of kn (the package's
    ``REGULARISATION``; another value only to study where the steps land, studies/diagnose_hybrid_paths.py)."""
    schema = net.schema
    feats, m, unbalanced, old = features_and_contacts(schema, net.active_index, cell_size, free_position,
                                                      shear_force, d_eps, net.load_features)
    d_net = net.displacement_from_features(feats, m, unbalanced, torch.clamp(m / RELAXATION_RAMP, max=1.0))
    new_size = cell_size * (1.0 - d_eps)
    d_net, _ = cell_physics.hold_at_rest(schema, new_size.detach(), free_position, d_net, old)
    state = (cell_size, free_position, shear_force)
    probe = m.reshape(-1).detach()
    active = probe >= RELAXATION_RAMP
    n = cell_size.shape[0]
    ratios = torch.zeros(2, n, dtype=cell_size.dtype, device=cell_size.device)
    steps = torch.zeros(n, dtype=torch.int64, device=cell_size.device)
    shortened = torch.zeros_like(steps)
    shifted = torch.zeros_like(steps)
    d = d_net.detach().clone()
    eye = torch.eye(d.shape[1], dtype=d.dtype, device=d.device)
    residual = jac = None
    for step in range(int(iterations) + 1):
        residual, fn_max, jac = _jacobian(schema, state, d_eps, d, old)
        ratio = torch.where(fn_max > 0, residual.abs().amax(dim=1) / torch.where(fn_max > 0, fn_max, 1.0),
                            torch.zeros_like(fn_max))
        ratio = torch.where(active, ratio, torch.zeros_like(ratio))
        if step == 0:
            ratios[0] = ratio
        ratios[1] = torch.where(active, ratio, ratios[1])
        active = active & (ratio > tolerance) & (step < int(iterations))
        if not bool(active.any()):
            break
        delta = torch.zeros_like(d)
        full = torch.zeros_like(active)
        delta[active], full[active] = _downhill(-jac[active] + regularisation * schema.kn * eye, residual[active],
                                                shift * schema.kn)
        steps[active] += 1
        shifted += full.to(shifted.dtype)
        d = _line_search(schema, state, d_eps, d, delta, residual, active & ~full, active & full, halvings, old,
                         shortened)
    if d_eps.requires_grad:
        corrected = steps > 0
        with torch.enable_grad():
            r_eps, _ = balance(schema, *state, d_eps, d, old)
        _, _, jac = _jacobian(schema, state, d_eps, d, old)
        delta = torch.linalg.solve(-jac + regularisation * schema.kn * eye, r_eps.unsqueeze(-1)).squeeze(-1)
        implicit = d + (delta - delta.detach())
        d = torch.where(corrected.unsqueeze(-1), implicit, d_net)
    else:
        d = torch.where((probe >= RELAXATION_RAMP).unsqueeze(-1), d, d_net)
    inc = cell_physics.advance(schema, cell_size, free_position, shear_force, d_eps, d, old, rest_rule=True)
    return Corrected(inc, ratios, steps, shortened, shifted)
