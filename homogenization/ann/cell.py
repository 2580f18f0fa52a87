"""Generic meso-ANN backend (spec section 12): a trained ``MesoNet`` decides every cell-increment.

``AnnCell`` implements ``warp_hcell.core.contract.CellModel`` for ANY mesostructure the model
was trained on, planar or spatial (the dimension is the model's schema's). The state of a cell
is the DEM's learning state: cell size (l1, l2[, l3]), the free-DOF coordinates and the
tangential spring force of every candidate pair (a vector per pair in 3D). Per macro
increment, ONE batched network call over all cells gives the free-DOF displacement (a rate
per unit probe magnitude plus a learned relaxation of the unbalanced forces, see
``training.network``); then exact generic physics (``training.cell_physics``) follows:

- the cell size follows the imposed strain, l <- l (1 - d_eps), and the driven DOFs follow
  the cell size (x = x_ref l / l_ref);
- normal forces, contact flags and tangential forces come from the contact law of the DEM
  (tangential increment along the mid-increment tangent, Coulomb cap from the trial force,
  reset out of contact); the moment is the Love-Weber sum over the contacts and V_cell the
  area of the polygon through the outer grains (the volume of the outer polyhedron in 3D).

On CPU, ``step`` runs a cell's increment through ``training.inference.FastAdvance`` (the same
physics compiled with numba around the network call; equal to the torch path up to rounding),
and a planar cell's tangent by forward-mode differentiation in the same code, a corrected spatial
cell's as the derivative of its balanced end state (``FastAdvance.has_tangent``); the tangent of a
spatial network alone, and everything on another device, through the torch path and autograd. The compiled
path reads the model's weights without torch (``training.fast_model``); the torch network
(``AnnCell.net``) is rebuilt from the same files the first time something needs it.

No equilibrium is solved and no closed form of a particular cell is used, unless asked or
certified: ``equilibrium_corrections=K`` (spatial cells; None, the default: the K and tolerance
that the model's certificate measured, ``envelope.equilibrium_settings``, 0 without one) takes the network's free-DOF displacement as the
first guess of up to K exact Newton steps on the balance of the free DOFs with the exact contact
law (``training.fast_equilibrium3d``, ``training.equilibrium``), in the cells whose force ratio
(largest unbalanced free-DOF force over the largest normal force) exceeds
``equilibrium_tolerance`` (default: the DEM's ``force_tolerance``). That hybrid is another
surrogate than the network alone: its diagnostics add ``n_corrected`` (cells corrected),
``n_corrections`` (Newton steps), ``n_shortened`` and ``n_shifted`` (those of them the line search
shortened, and those whose matrix was shifted; ``training.fast_equilibrium3d``),
``n_unconverged`` (cells still above the tolerance after them),
``force_ratio_network_max`` and ``force_ratio_max`` (the largest force ratio before and after) and
``n_escalated`` (cells handed to the DEM's own increment from rest because a free grain moved and ends
touching nothing, which the corrections cannot place: ``homogenization.ann.escalation``; off with
``dem_escalation=False``; on CPU ``n_released`` cells taken again with that grain at rest instead, and under
``escalation.RELEASE_RULE`` ``n_resting`` cells whose grains nothing pressed started the corrections at rest;
under ``escalation.RELEASE_RULE_DRAG`` also ``n_relaxed`` cells whose grains, pushed from rest, were relaxed as the
DEM relaxes them from rest, with ``n_relaxed_substeps`` and ``n_relaxed_unconverged``),
and the model's certificate covers it only where that certificate measured this very hybrid
(``hmodel certify --equilibrium-corrections K``: same K and tolerance; ``certificate_problem`` says
otherwise, as it does for a run of the network alone under a certificate of the hybrid). Each ``step``
reports in ``CellResponse.diagnostics`` how many cells a branch of the contact law touched:
``n_coulomb_capped`` (a trial tangential force exceeded mu f_n), ``n_tension_clipped`` (a
contact carrying a normal force opened: no tension), ``n_mechanism`` (cells carrying no
contact force after the increment), ``n_relaxation_scaled`` (probes smaller than
``training.network.RELAXATION_RAMP``, whose relaxation of unbalanced forces is scaled down
so that a zero increment is a no-op, as stress control assumes) and ``n_grains_held`` (free
grains, summed over the cells, that carried no force and that nothing reached, held at rest
instead of moved by the network: the DEM's rest rule, ``training.cell_physics.hold_at_rest``).

The model records the mesostructure it was trained on (description and sha256) and the cells
its database was explored from. ``init_state(mesostructure, n_cells)`` starts the cells from
a mesostructure whose hash equals the model's, or from a cell of the same learning state whose
start state lies within the range of those start cells (e.g. an H-cell at an opening angle
between the database's; ``training.checkpoint.check_start_cell``). Otherwise
``CheckpointError`` (one line; exit code 2 in the CLIs).

The certificate and its envelope (``homogenization.ann.policy.CertificatePolicy``) and the
out-of-distribution checks (``homogenization.ann.ood.OodMonitor``) stand beside the cell, which
reports them (``certificate``, ``certificate_problem``, ``envelope``, ``envelope_exits``, ``ood``).

Sign convention: compression and contraction positive. Local frame: index 0 = n, 1 = t
(3D: 1 = t1, 2 = t2).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, NamedTuple, Sequence, TYPE_CHECKING

import numpy as np

from homogenization.ann import default_model_path, envelope
from homogenization.ann.escalation import DemEscalation, RELAX_SUBSTEPS, RELEASE_RULE, RELEASE_RULE_DRAG, RELEASE_RULES
from homogenization.ann.ood import OOD_INTERVAL, OodMonitor
from homogenization.ann.policy import CertificatePolicy, default_escalation
from homogenization.ann.records import Certificate, certificate_of
from training import fast_model
from training.inference import Corrections, FastAdvance
from training.fast_model import net_arrays, RELAXATION_RAMP, StateDictError
from training.checkpoint import check_compatible, check_start_cell, CheckpointError, load_checkpoint, read_metadata
from training.ood import OodIndex, probe_columns, state_features
from warp_hcell.core.contract import ArrayStateMixin, CellResponse
from warp_hcell.mesostructures.files import from_description
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES, cell_measure, evaluate_observables, Mesostructure, per_cell
from warp_hcell.core.parameters import check_positive, ContactLaw, DemSettings, require_linear_law

if TYPE_CHECKING:
    from training.card import ModelCard  # the type of an argument only


TANGENT_MISS = 0.5
"""Relative miss of a cell's tangent against its secant over the second half of an increment beyond
which ``AnnCell.failed_cells`` counts the tangent as off the step [-]."""
DIAGNOSED_CELLS = 5
"""Failed cells named in the one-line diagnosis of a failed stress control (the rest are counted)."""


class AnnState(NamedTuple):
    """Batch of generic ANN cells (first axis n_cells)."""

    cell_size: np.ndarray
    """(l1, l2[, l3]) [m], shape (n_cells, dim)."""
    free_position: np.ndarray
    """Free-DOF coordinates [m], shape (n_cells, n_free), in the model's ``free_dofs`` order."""
    shear_force: np.ndarray
    """Tangential spring force of every candidate pair [N], shape (n_cells, n_pairs) (3D:
    (n_cells, n_pairs, 3)), DEM convention."""


class AnnCell(ArrayStateMixin):
    """Cells whose increments are decided by a trained ``training.network.MesoNet``.

    Args:
        contact_law: the contact law of the model's training data.
        radius: grain radius r [m], > 0; unused (the mesostructure sets it).
        model: a model's ``.pt`` (its ``.json`` beside it); None: the shipped one.
        device: torch device ("cpu", "cuda", ...). threads: torch CPU threads (process-wide).
        ood_interval: start states between out-of-distribution checks, >= 1.
        equilibrium_corrections: most Newton steps on the free DOFs' balance after the network's
            (spatial models); 0: the network alone; None: the certificate's K.
        equilibrium_tolerance: force ratio above which a cell is corrected [-]; None: the
            certificate's, else the DEM's.
        dem_escalation: with K > 0, the released grains' rule (``ann.escalation``); None: the
            certificate's choice, else ``default_escalation``.
        release_rule: one of ``escalation.RELEASE_RULES``; None: the certificate's, else ``RELEASE_RULE``.
        card: ``model``'s JSON already read, or None.

    Raises:
        CheckpointError: (ValueError, one line) a missing, corrupt or mismatched model, another
            contact law; ``init_state``: another mesostructure.
    """

    name = "ann"
    state_type = AnnState
    default_dim = 2
    """Dimension of the cells whose shipped model ``model=None`` loads."""

    def __init__(self, contact_law: ContactLaw, radius: float, *, model: str | Path | None = None,
                 device: str = "cpu", threads: int = 1, ood_interval: int = OOD_INTERVAL,
                 equilibrium_corrections: int | None = None, equilibrium_tolerance: float | None = None,
                 dem_escalation: bool | None = None, card: ModelCard | None = None,
                 release_rule: str | None = None) -> None:
        require_linear_law(contact_law, "the meso-ANN backend (its networks learn from DEM databases of the linear law)")
        self.contact_law = contact_law
        self.radius = check_positive("radius", radius)
        if int(threads) < 1:
            raise ValueError(f"threads = {threads} must be >= 1")
        path = default_model_path(self.default_dim) if model is None else Path(model)
        if model is None and not path.is_file():
            raise CheckpointError(f"{path}: the default {self.default_dim}D ANN model is not installed; pass "
                                  f"model=PATH (--model)")
        if not path.is_file():
            raise CheckpointError(f"{path}: no such model file")
        self.metadata = read_metadata(path) if card is None else card.to_dict()
        try:
            arrays = net_arrays(path, self.metadata)
        except StateDictError as exc:
            raise CheckpointError(str(exc)) from None
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise CheckpointError(f"{path}: cannot rebuild the network ({exc})") from None
        self.arrays = arrays
        """The network as numpy arrays, read without torch (``training.fast_model.NetArrays``)."""
        check_compatible(self.metadata, kn=contact_law.kn, kt_over_kn=contact_law.kt_over_kn,
                         phi_g_deg=contact_law.phi_g_deg, source=str(path))
        self.trained_on = from_description(self.metadata["mesostructure"])
        self.model_path = path
        self.device_name = str(device)
        self._net = None
        self.threads = int(threads)
        if not self.device_name.startswith("cpu"):
            self.net  # noqa: B018 (another device: the torch network now, so that a bad device fails here)
        self.dim = self.arrays.schema.dim
        if equilibrium_corrections is None:
            certified = certificate_of(self.metadata)
            equilibrium_corrections, measured_tolerance = (envelope.equilibrium_settings(certified)
                                                           if certified is not None else (0, None))
            if equilibrium_tolerance is None:
                equilibrium_tolerance = measured_tolerance
            if dem_escalation is None and certified is not None:
                dem_escalation = envelope.escalation_of(certified)
        if int(equilibrium_corrections) < 0 or (int(equilibrium_corrections) > 0 and self.dim != 3):
            raise ValueError(f"equilibrium corrections = {equilibrium_corrections}: a count >= 0, and > 0 for a "
                             f"spatial model only ({path.name} is {self.dim}D)")
        self.equilibrium_corrections = int(equilibrium_corrections)
        self.force_tolerance = DemSettings().force_tolerance if equilibrium_tolerance is None else float(equilibrium_tolerance)
        if not self.force_tolerance > 0:
            raise ValueError(f"equilibrium tolerance = {equilibrium_tolerance} must be > 0")
        self.fast = (FastAdvance(self.arrays, self.equilibrium_corrections, self.force_tolerance)
                     if self.device_name.startswith("cpu") else None)
        self.escalation = (DemEscalation(self.trained_on, contact_law, float(self.metadata["contact_tolerance"]),
                                         force_ratio=self.force_tolerance)
                           if self.equilibrium_corrections and (default_escalation(self.metadata)
                                                                if dem_escalation is None else dem_escalation)
                           else None)
        certified = certificate_of(self.metadata)
        recorded = None if certified is None else envelope.escalation_rule_of(certified)
        if release_rule is None:
            release_rule = recorded if recorded in RELEASE_RULES else RELEASE_RULE
        if release_rule not in RELEASE_RULES:
            raise ValueError(f"release rule {release_rule!r}: one of {RELEASE_RULES}")
        self.release_rule = release_rule
        """What the hybrid does with the grains nothing presses (``homogenization.ann.escalation.RELEASE_RULES``)."""
        self.policy = CertificatePolicy(self.metadata, path, self.dim, self.equilibrium_corrections,
                                        self.force_tolerance, self.escalation is not None, self.release_rule)
        """The certificate and its envelope (``homogenization.ann.policy.CertificatePolicy``)."""
        if self.escalation is not None and self.fast is None and self.policy.problem is None:
            self.policy.problem = (f"{path}: its certificate measured the hybrid's released-grain rule, which runs "
                                   f"on CPU only; on {self.device_name} a released cell takes the DEM's increment "
                                   f"instead (run with --device cpu)")
        self.ood_monitor = OodMonitor(self.arrays, path, ood_interval)
        """The out-of-distribution checks (``homogenization.ann.ood.OodMonitor``)."""

    @property
    def net(self):
        """The model's ``training.network.MesoNet`` on this cell model's device, rebuilt with torch
        (``training.checkpoint.load_checkpoint``) the first time it is asked for; sets torch's CPU threads."""
        if self._net is None:
            import torch  # noqa: PLC0415 (only the torch path and autograd need it)

            with torch.inference_mode(False):  # first asked for inside inference mode: still a network autograd can use
                net, _ = load_checkpoint(self.model_path, self.metadata)
            device = torch.device(self.device_name)
            net.to(device)
            net.schema = net.schema.to(device)
            net.active_index = net.active_index.to(device)
            torch.set_num_threads(self.threads)
            self._net = net
        return self._net

    @property
    def device(self):
        """The torch device of the torch path (imports torch)."""
        import torch  # noqa: PLC0415

        return torch.device(self.device_name)

    @property
    def certificate(self) -> Certificate | None:
        """The model JSON's certificate (None: uncertified)."""
        return self.policy.certificate

    @property
    def certificate_problem(self) -> str | None:
        """Why the model may not be used for this surrogate and these cells, one line
        (``homogenization.ann.policy.certificate_problem``), or None."""
        return self.policy.problem

    @property
    def envelope(self) -> dict[str, Any] | None:
        """The certificate's envelope (``homogenization.ann.envelope.envelope_of``); None uncertified."""
        return self.policy.envelope

    def envelope_exits(self, programme: Sequence[Any], meso: Mesostructure) -> list[str] | None:
        """Where ``programme`` run on cells of ``meso`` leaves the certificate's envelope
        (``CertificatePolicy.envelope_exits``); None for an uncertified model."""
        return self.policy.envelope_exits(programme, meso)

    @property
    def ood(self) -> OodIndex | None:
        """The out-of-distribution index beside the model (None: no checks)."""
        return self.ood_monitor.index

    @property
    def ood_counts(self) -> np.ndarray:
        """Cumulative (cells beyond the threshold, cells checked) over this cell model's checks."""
        return self.ood_monitor.counts

    # -- construction ---------------------------------------------------------------------
    def check_trained_on(self, meso: Mesostructure) -> None:
        """Raise ``CheckpointError`` (one line) unless the model may start cells from ``meso``
        (``training.checkpoint.check_start_cell``: its database's mesostructure, or a cell of
        the same learning state within the range of the cells the database started from). A 3D cell driven
        with other kinematics than the certificate's tests leaves the certificate: ``certificate_problem``
        says so (``CertificatePolicy.check_kinematics``)."""
        check_start_cell(self.metadata, meso, source=str(self.model_path))
        self.policy.check_kinematics(meso)

    @property
    def certified_kinematics(self) -> str:
        """The kinematics of the cells of the certificate's tests (``CertificatePolicy.certified_kinematics``)."""
        return self.policy.certified_kinematics

    # -- CellModel protocol ---------------------------------------------------------------
    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int) -> AnnState:
        """Touching, force-free cells of ``mesostructure`` (one, or one per cell); ``check_trained_on`` first."""
        distinct, index = per_cell(mesostructure, n_cells)
        for meso in distinct:
            self.check_trained_on(meso)
        position = np.stack([meso.position for meso in distinct])[index]
        cell_size = np.stack([meso.cell_size for meso in distinct])[index]
        free = self.arrays.schema.free_dofs
        return AnnState(np.array(cell_size, dtype=np.float64), np.array(position[:, free[:, 0], free[:, 1]]),
                        np.zeros((int(n_cells), *self.arrays.schema.shear_shape)))

    def _tensors(self, state: AnnState):
        import torch  # noqa: PLC0415

        return tuple(torch.from_numpy(np.asarray(a, dtype=np.float64)).to(self.device) for a in state)

    def step(self, state: AnnState, d_eps_local: np.ndarray, *, with_tangent: bool = False) -> tuple[AnnState, CellResponse]:
        """Advance every cell by its local strain increment with one network call; pure.

        Args:
            state: cells at the start of the increment.
            d_eps_local: local strain increment [-], shape (n_cells, dim), compression positive.
            with_tangent: also return ``CellResponse.tangent`` = d(S_nn, S_tt[, S_t2t2])/d(d_eps)
                [N m], shape (n_cells, dim, dim), the derivative of the whole increment (network
                and contact law): compiled on CPU where ``FastAdvance.has_tangent`` (planar cells; spatial
                cells with corrections), torch autograd otherwise (on CPU the state and moment stay the
                compiled step's, whether a tangent is asked or not).

        Returns:
            The state at the end of the increment and its response (diagnostics: module docstring).
        """
        due = self.ood_monitor.due(state)
        if self.fast is not None:
            resting = self._resting(state)
            compiled = with_tangent and self.fast.has_tangent
            inc, tangent = self.fast.increment(*state, d_eps_local, compiled, held=resting)
            if with_tangent and not compiled:  # the compiled step's state, torch's tangent (a search direction)
                tangent = self._torch_step(state, d_eps_local, True)[2]
            features = self.fast.last_features()[probe_columns(self.arrays):].T if due else None
            tally = _Tally.of(inc, self.fast.last_corrections(), self.fast.last_counts())
            diagnostics = {**tally.diagnostics(self.force_tolerance), **self.ood_monitor.diagnostics(due, state, features)}
            return self._escalated(state, d_eps_local, AnnState(inc.cell_size, inc.free_position, inc.shear_force),
                                   CellResponse(inc.moment, inc.area, diagnostics, tangent), resting, tally)
        from training import cell_physics  # noqa: PLC0415

        step, counts, tangent = self._torch_step(state, d_eps_local, with_tangent)
        new = AnnState(*(t.detach().cpu().numpy() for t in (step.cell_size, step.free_position, step.shear_force)))
        moment = step.moment.detach().cpu().numpy()
        flags = [step.capped.any(dim=1).cpu().numpy(), step.opened.any(dim=1).cpu().numpy(),
                 np.all(moment == 0.0, axis=(1, 2)), np.linalg.norm(d_eps_local, axis=1) < RELAXATION_RAMP,
                 cell_physics.count_held_grains(self.net.schema, step.held).cpu().numpy()]
        tally = _Tally(flags, None if counts[0] is None else Corrections(*(c.detach().cpu().numpy() for c in counts)))
        diagnostics = {**tally.diagnostics(self.force_tolerance),
                       **self.ood_monitor.diagnostics(due, state, state_features(self.net, *state) if due else None)}
        return self._escalated(state, d_eps_local, new,
                               CellResponse(moment, step.area.detach().cpu().numpy(), diagnostics, tangent))

    def _torch_step(self, state: AnnState, d_eps_local: np.ndarray, with_tangent: bool) -> tuple[Any, tuple, Any]:
        """The torch increment (``_advance``) of ``state`` by ``d_eps_local`` (n, dim): (its outcome, its
        corrections' counts, the tangent (n, dim, dim) [N m] by autograd where ``with_tangent``, else None)."""
        import torch  # noqa: PLC0415

        size, free, shear = self._tensors(state)
        d_eps = torch.as_tensor(np.asarray(d_eps_local, dtype=np.float64), device=self.device)
        if not with_tangent:
            with torch.inference_mode() if not self.equilibrium_corrections else torch.no_grad():
                return (*self._advance(size, free, shear, d_eps), None)
        d_eps = d_eps.clone().requires_grad_(True)
        step, counts = self._advance(size, free, shear, d_eps)
        rows = [torch.autograd.grad(step.moment[:, i, i].sum(), d_eps, retain_graph=i < self.dim - 1)[0]
                for i in range(self.dim)]
        return step, counts, torch.stack(rows, dim=1).detach().cpu().numpy()

    def _resting(self, state: AnnState) -> np.ndarray | None:
        """bool (n, n_free): the free DOFs that start the corrections at rest under ``RELEASE_RULE``, those of the
        grains nothing presses at the start (``DemEscalation.resting_dofs``); None under another rule or without
        the escalation."""
        if self.escalation is None or self.release_rule not in (RELEASE_RULE, RELEASE_RULE_DRAG):
            return None
        return self.escalation.resting_dofs(state.cell_size, state.free_position)

    def _escalated(self, state: AnnState, d_eps_local: np.ndarray, new: AnnState, response: CellResponse,
                   resting: np.ndarray | None = None, tally: _Tally | None = None) -> tuple[AnnState, CellResponse]:
        """``new`` and ``response`` where a grain is released (``DemEscalation.released``; hybrids with
        ``dem_escalation`` only, counted in ``n_released``): on CPU the increment again from rest for that grain
        (``_held_at_rest``) unless it started there (``resting``, (n, n_free) bool; cells with one counted in
        ``n_resting``, the released among them in ``n_released_pushed``), on another device the DEM's increment,
        as with ``sliding`` the sliding cells (counted in ``n_escalated``; those whose DEM did not reach equilibrium in
        ``n_escalated_unconverged``). The tangent of such a cell stays the
        hybrid's (stress control's search direction only). ``tally``: the compiled step's per-cell counts, whose
        cells taken again on CPU count as they end (``_Tally``)."""
        if self.escalation is None:
            return new, response
        released = self.escalation.released_dofs(new.cell_size, state.free_position, new.free_position)
        escalated = released.any(axis=1)
        response.diagnostics["n_released"] = float(np.count_nonzero(escalated))
        response.diagnostics["n_released_pushed"] = 0.0
        drag = self.release_rule == RELEASE_RULE_DRAG and resting is not None and self.fast is not None
        if resting is not None:
            response.diagnostics["n_resting"] = float(np.count_nonzero(resting.any(axis=1)))
            again = (released & ~resting).any(axis=1)
            pushed = float(np.count_nonzero(escalated & ~again))  # started at rest, pushed, released: the rule's end
            pushed_dofs = released & resting if drag else None
            released |= resting
            escalated = again
        if escalated.any() and self.fast is not None:
            index = np.flatnonzero(escalated)
            new, response = self._held_at_rest(state, d_eps_local, new, response, index, released, tally)
            if drag:
                pushed_dofs[index] = released[index] & self.escalation.released_dofs(
                    new.cell_size[index], np.asarray(state.free_position)[index], new.free_position[index])
            escalated = np.zeros_like(escalated)
        if drag:
            new, response = self._dragged(state, d_eps_local, new, response, pushed_dofs, tally)
        if tally is not None:
            response.diagnostics.update(tally.diagnostics(self.force_tolerance))
        if resting is not None:
            response.diagnostics["n_released_pushed"] += pushed
        if self.escalation.with_sliding:
            escalated |= self.escalation.sliding(new.cell_size, new.free_position, new.shear_force)
        response.diagnostics["n_escalated"] = float(np.count_nonzero(escalated))
        response.diagnostics["n_escalated_unconverged"] = 0.0
        if not escalated.any():
            return new, response
        index = np.flatnonzero(escalated)
        size, free, shear, moment, area, converged = self.escalation.advance(
            state.cell_size[index], state.free_position[index], state.shear_force[index],
            np.asarray(d_eps_local, dtype=np.float64)[index])
        response.diagnostics["n_escalated_unconverged"] = float(np.count_nonzero(~converged))
        return _with_cells(new, response, index, (size, free, shear, moment, area))

    def _dragged(self, state: AnnState, d_eps_local: np.ndarray, new: AnnState, response: CellResponse,
                 pushed: np.ndarray, tally: _Tally | None) -> tuple[AnnState, CellResponse]:
        """``new`` and ``response`` where the free DOFs ``pushed`` (n, n_free) bool (grains that started the
        corrections at rest and end released) move as the DEM's relaxation from rest moves them, the other grains
        following the balance (``DemEscalation.relaxed``), then the contact law at the end
        (``FastAdvance.again_displaced``). Counts ``n_relaxed`` (cells), ``n_relaxed_substeps`` and
        ``n_relaxed_unconverged`` (cells that reached ``RELAX_SUBSTEPS``)."""
        cells = np.flatnonzero(pushed.any(axis=1))
        diagnostics = response.diagnostics
        diagnostics["n_relaxed"] = float(cells.size)
        diagnostics["n_relaxed_substeps"] = 0.0
        diagnostics["n_relaxed_unconverged"] = 0.0
        if not cells.size:
            return new, response
        free0 = np.asarray(state.free_position)[cells]
        schema = self.arrays.schema
        free, substeps = self.escalation.relaxed(
            fast_model.positions(schema, np.asarray(state.cell_size)[cells], free0),
            fast_model.positions(schema, new.cell_size[cells], new.free_position[cells]),
            np.asarray(state.shear_force)[cells], np.asarray(d_eps_local, dtype=np.float64)[cells], pushed[cells])
        diagnostics["n_relaxed_substeps"] = float(substeps.sum())
        diagnostics["n_relaxed_unconverged"] = float(np.count_nonzero(substeps >= RELAX_SUBSTEPS))
        inc = self.fast.again_displaced(cells, free - free0)
        if tally is not None:
            tally.take(cells, inc, None)
        return _with_cells(new, response, cells, (inc.cell_size, inc.free_position, inc.shear_force, inc.moment,
                                                  inc.area))

    def _held_at_rest(self, state: AnnState, d_eps_local: np.ndarray, new: AnnState, response: CellResponse,
                      index: np.ndarray, released: np.ndarray, tally: _Tally | None) -> tuple[AnnState, CellResponse]:
        """``new`` and ``response`` with the increment of the cells ``index`` taken again, the DOFs of their
        released grains (``released`` (n, n_free) bool) starting the corrections at rest
        (``FastAdvance.again_at_rest``): a grain that nothing pushes stays where it was, one that a
        neighbour pushes moves as far as the balance needs. Counts ``n_released_pushed`` (cells with a
        released grain again after it); ``tally`` takes those cells as they end, their corrections added."""
        inc = self.fast.again_at_rest(index, released[index])
        response.diagnostics["n_released_pushed"] = float(np.count_nonzero(
            self.escalation.released(inc.cell_size, np.asarray(state.free_position)[index], inc.free_position)))
        if tally is not None:
            tally.take(index, inc, self.fast.last_corrections())
        return _with_cells(new, response, index, (inc.cell_size, inc.free_position, inc.shear_force, inc.moment,
                                                  inc.area))

    def _advance(self, size, free, shear, d_eps):
        """The torch increment (``MesoNet.advance``, or ``training.equilibrium.corrected_advance`` with
        equilibrium corrections) and its (force ratios, corrections) (None, None without)."""
        if not self.equilibrium_corrections:
            return self.net.advance(size, free, shear, d_eps), (None,) * 4
        from training.equilibrium import corrected_advance  # noqa: PLC0415

        out = corrected_advance(self.net, size, free, shear, d_eps, self.equilibrium_corrections, self.force_tolerance)
        return out.increment, (out.force_ratio, out.corrections, out.shortened, out.shifted)

    def failed_cells(self, state: AnnState, d_eps_local: np.ndarray) -> dict[str, np.ndarray]:
        """The cells whose step or tangent fails over the increment ``d_eps_local`` (n, dim) from ``state``.

        Returns bool arrays (n,): ``step`` (a non-finite moment after the increment), ``tangent`` (a
        non-finite tangent) and ``off`` (the tangent at the end of the increment misses the change of
        the diagonal moments over its second half, S(d) - S(d / 2), by more than ``TANGENT_MISS`` of the
        larger of the two and by more than 1e-6 of the cell's largest moment: a contact opening,
        closing or starting to slide inside the increment, where Newton's method meets a kink)."""
        d = np.asarray(d_eps_local, dtype=np.float64)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            _, full = self.step(state, d, with_tangent=True)
            _, half = self.step(state, 0.5 * d)
            diagonal = lambda m: np.diagonal(np.asarray(m), axis1=1, axis2=2)  # noqa: E731
            secant = diagonal(full.moment) - diagonal(half.moment)
            predicted = 0.5 * np.einsum("nab,nb->na", np.asarray(full.tangent), d)
            scale = np.abs(np.asarray(full.moment)).max(axis=(1, 2))
            miss = np.abs(secant - predicted)
            off = np.any((miss > TANGENT_MISS * np.maximum(np.abs(secant), np.abs(predicted)))
                         & (miss > 1e-6 * scale[:, None]), axis=1)
        step = ~np.isfinite(np.asarray(full.moment)).all(axis=(1, 2)) | ~np.isfinite(np.asarray(half.moment)).all(axis=(1, 2))
        tangent = ~np.isfinite(np.asarray(full.tangent)).all(axis=(1, 2))
        return {"step": step, "tangent": tangent & ~step, "off": off & ~step & ~tangent}

    def unbalanced_cells(self, state: AnnState, d_eps_local: np.ndarray) -> np.ndarray:
        """Force ratio (n,) after the equilibrium corrections of the increment ``d_eps_local`` (n, dim) from
        ``state``, the largest unbalanced free-DOF force over the largest normal force [-] (0 where not
        evaluated); zeros without corrections."""
        d = np.asarray(d_eps_local, dtype=np.float64)
        if not self.equilibrium_corrections:
            return np.zeros(d.shape[0])
        if self.fast is not None:
            self.fast.increment(*state, d, False, held=self._resting(state))
            return np.asarray(self.fast.last_corrections().force_ratio[1])
        import torch  # noqa: PLC0415

        size, free, shear = self._tensors(state)
        with torch.no_grad():
            _, (ratio, *_) = self._advance(size, free, shear, torch.as_tensor(d, device=self.device))
        return ratio[1].cpu().numpy()

    def control_diagnosis(self, state: AnnState, d_eps_local: np.ndarray, directions: np.ndarray,
                          programme: Sequence[Any], meso: Mesostructure) -> str:
        """One line on a stress-controlled increment that failed (``homogenization.element_test.driver``): how many
        cells, which (indices and cell axes ``directions`` (n, dim), unit vectors in the macro frame),
        failed their step or tangent over the last trial (``failed_cells``), with equilibrium corrections
        which cells the corrections left above their tolerance over it (``unbalanced_cells``: their step
        may jump and their tangent miss it), whether the model is certified and whether the run lies
        inside its certificate's envelope."""
        failed = self.failed_cells(state, d_eps_local)
        ratio = self.unbalanced_cells(state, d_eps_local)
        failed["unbalanced"] = ratio > self.force_tolerance
        n = np.asarray(d_eps_local).shape[0]
        parts = []
        for key, what in (("step", "non-finite step"), ("tangent", "non-finite tangent"),
                          ("off", f"tangent off the step by > {TANGENT_MISS:.0%}"),
                          ("unbalanced", f"force ratio above {self.force_tolerance:g} after K = "
                                         f"{self.equilibrium_corrections} equilibrium corrections")):
            index = np.flatnonzero(failed[key])
            if index.size:
                ratios = key == "unbalanced"
                shown = ", ".join(f"{k} (n = ({', '.join(f'{v:.2f}' for v in directions[k])})"
                                  + (f", ratio {ratio[k]:.2g})" if ratios else ")") for k in index[:DIAGNOSED_CELLS])
                parts.append(f"{what} in {index.size} of {n} cells: {shown}{', ...' if index.size > DIAGNOSED_CELLS else ''}")
        cells = "; ".join(parts) if parts else f"no cell of {n} failed its step or tangent over the last trial"
        verdict = self.policy.standing()
        exits = self.envelope_exits(programme, meso)
        where = ("no envelope" if exits is None else "run inside its envelope" if not exits
                 else f"run outside its envelope ({'; '.join(exits)})")
        return f"ANN diagnosis: {cells}; {verdict}, {where}"

    def _forces(self, state: AnnState):
        """Grain centres, ``training.fast_model.Contacts`` and pair forces of ``state`` (numpy)."""
        schema = self.arrays.schema
        x = fast_model.positions(schema, state.cell_size, np.asarray(state.free_position, dtype=np.float64))
        c = fast_model.contacts(schema, x)
        return x, c, fast_model.pair_forces(c, np.asarray(state.shear_force, dtype=np.float64))

    def response(self, state: AnnState) -> CellResponse:
        """Meso-stress of ``state`` without advancing it (the contact law on numpy arrays)."""
        x, c, force = self._forces(state)
        return CellResponse(fast_model.love_weber(c, force), cell_measure(x, self.arrays.schema.outer))

    def observables(self, state: AnnState) -> dict[str, np.ndarray]:
        """Per-cell quantities, shape (n_cells,) each.

        Always ``l1, l2, area`` [m, m^2], ``S_nn, S_tt, S_nt`` [N m] (compression positive),
        ``n_contacts`` and grain centres ``x_n{i}, x_t{i}`` [m] (i = 1-based label), and the
        observables the model's mesostructure declares (``Mesostructure.observables``). A
        spatial cell gives, as the DEM backend, ``l1, l2, l3``, ``area`` (the volume [m^3]),
        ``S_nn, S_t1t1, S_t2t2, S_nt1, S_nt2, S_t1t2`` and ``x_n{i}, x_t1{i}, x_t2{i}`` instead.
        """
        x, c, force = self._forces(state)
        response = CellResponse(fast_model.love_weber(c, force), cell_measure(x, self.arrays.schema.outer))
        axes = AXIS_NAMES[self.dim]
        obs: dict[str, np.ndarray] = {f"l{k + 1}": state.cell_size[:, k].copy() for k in range(self.dim)}
        obs["area"] = response.area
        for a, b in ((0, 0), *((k, k) for k in range(1, self.dim)), *((a, b) for a in range(self.dim)
                                                                       for b in range(a + 1, self.dim))):
            obs[f"S_{axes[a]}{axes[b]}"] = response.moment[:, a, b]
        obs["n_contacts"] = c.contact.sum(axis=1)
        if self.trained_on.observables:
            obs.update(evaluate_observables(self.trained_on, x, c.normal_force, state.shear_force, c.contact))
        for g in range(x.shape[1]):
            for k, axis in enumerate(axes):
                obs[f"x_{axis}{g + 1}"] = x[:, g, k].copy()
        return obs


class AnnCell3D(AnnCell):
    """``AnnCell`` whose ``model=None`` is the shipped model of spatial cells (``DEFAULT_MODELS[3]``):
    the backend ``ann`` of 3D runs (``homogenization.backends.BACKENDS``)."""

    default_dim = 3


class _Tally:
    """The counts of one step, so that a cell taken again (``AnnCell._held_at_rest``, ``_dragged``) counts as it
    ends: the branch flags per cell (``training.inference.FastIncrement``: capped, opened, mechanism,
    relaxation-scaled, grains held; ``counts``, their sums where given, until a cell is taken again) and the
    equilibrium corrections (``training.inference.Corrections``: the force ratios as they end, the Newton steps,
    shortened and shifted of every pass added). The arrays are copied before the first cell is taken again."""

    def __init__(self, flags: list[np.ndarray], corrections: Corrections | None, counts: list[int] | None = None) -> None:
        self.flags = flags
        self.corrections = corrections
        self.counts = counts
        self.owned = False

    @classmethod
    def of(cls, inc: Any, corrections: Corrections | None, counts: np.ndarray) -> _Tally:
        """The tally of one ``FastAdvance.increment``'s outcome ``inc``, its ``last_corrections()`` and its
        ``last_counts()`` (read now)."""
        return cls(cls._flags_of(inc), corrections, counts.tolist())

    @staticmethod
    def _flags_of(inc: Any) -> list[np.ndarray]:
        """The per-cell branch flags of a ``FastIncrement``, in the tally's order."""
        return [inc.capped, inc.opened, inc.mechanism, inc.relaxation_scaled, inc.grains_held]

    def take(self, index: np.ndarray, inc: Any, corrections: Corrections | None) -> None:
        """Cells ``index`` as the pass ``inc`` (their outcome) ends them, its ``corrections`` (None: none taken)."""
        if not self.owned:
            self.flags = [np.array(a) for a in self.flags]
            if self.corrections is not None:
                self.corrections = Corrections(*(np.array(a) for a in self.corrections))
            self.counts, self.owned = None, True
        for whole, part in zip(self.flags, self._flags_of(inc)):
            whole[index] = part
        if corrections is not None and self.corrections is not None:
            self.corrections.force_ratio[1, index] = corrections.force_ratio[1]
            for whole, part in zip(self.corrections[1:], corrections[1:]):
                whole[index] += part

    def diagnostics(self, tolerance: float | None) -> dict[str, float]:
        """The step's counts (module docstring): the branch counts, and those of the corrections where taken."""
        capped, opened, mechanism, scaled, held = (
            self.counts or [np.count_nonzero(a) for a in self.flags[:4]] + [self.flags[4].sum()])
        counts = {"n_coulomb_capped": float(capped), "n_tension_clipped": float(opened), "n_mechanism": float(mechanism),
                  "n_relaxation_scaled": float(scaled), "n_grains_held": float(held)}
        if self.corrections is None:
            return counts
        ratio, steps, shortened, shifted = self.corrections
        return {**counts, "n_corrected": float(np.count_nonzero(steps)), "n_corrections": float(steps.sum()),
                "n_shortened": float(shortened.sum()), "n_shifted": float(shifted.sum()),
                "n_unconverged": float(np.count_nonzero(ratio[1] > tolerance)),
                "force_ratio_network_max": float(ratio[0].max(initial=0.0)),
                "force_ratio_max": float(ratio[1].max(initial=0.0))}


def _with_cells(new: AnnState, response: CellResponse, index: np.ndarray,
                parts: tuple[np.ndarray, ...]) -> tuple[AnnState, CellResponse]:
    """``new`` and ``response`` (this step's own arrays, written in place) whose cells ``index`` take ``parts``
    (cell_size, free_position, shear_force, moment, area of those cells, first axis len(index))."""
    for whole, part in zip((*new, response.moment, response.area), parts):
        whole[index] = part
    return new, response
