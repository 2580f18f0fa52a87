"""Fast inference of ``MesoNet.advance``: compiled cell physics around one MLP call, and its tangent.

``FastAdvance`` gives the same increment as ``MesoNet.advance`` (``training.network``,
``training.cell_physics``) up to float rounding, without torch:

1. ``training.fast_features`` (numba, float64, loops over cells innermost so that they
   vectorise): positions, contacts, pair forces, unbalanced forces and the z-scored features
   of the state before the increment;
2. the multilayer perceptron (``training.perceptron``: float32, one fixed sequence of fused
   multiply-adds per cell, no BLAS);
3. ``training.fast_increment`` (numba, float64): the free-DOF displacement from the network
   output, the new state by the contact law, its Love-Weber moment, area and contact-law
   branch flags;
4. on request, the consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t) by forward-mode
   differentiation of steps 1-3 (``training.fast_tangent``, ``Perceptron.jvp``), equal to
   torch autograd of ``MesoNet.advance`` up to the float32 rounding of the network.

Spatial cells (a schema of dimension 3) take ``training.fast_step3d`` for steps 1 and 3 (the
spring a vector in the tangent plane, V_cell a volume) around the same perceptron; the tangent
of their network is not compiled, that of their corrected increment is (``fast_equilibrium3d``).

The un-normalisation of the outputs and all the physics are float64 (positions must be
resolved to ~1e-7 D), so float32 only rounds the network's arithmetic (its effect on whole
runs is measured in ``docs/ann.md``). Every loop over cells is innermost, each cell one lane,
and nothing reduces across cells, so a cell's result is bit-identical whatever batch it is in,
wherever it sits in it and whatever the CPU's vector width (the cell contract's batch
invariance). The compiled kernels take the records of ``training.fast_tables``. The state arrays
returned are transposed views of cells-last arrays, so that the next increment reads them
without a copy.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t (3D: 1 = t1,
2 = t2).
"""

from __future__ import annotations

import gc
import importlib
import sys
import threading
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from training.fast_tables import Advanced, Before, CellTables, Normalisation, Physics
from training.fast_model import arrays_of_net, COMPLIANCE_SCALE, GAP_CLIP, NetArrays, RELAXATION_RAMP
from training.mlp import padded_cells, Perceptron
from training.precompiled import PrecompiledStep
from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import DemSettings


_FLOAT64, _BOOL, _INT64 = np.dtype(np.float64), np.dtype(np.bool_), np.dtype(np.int64)
"""dtype objects: numpy takes these faster than the scalar types (a positional dtype: the keyword is slower)."""


def _cells_last(values: np.ndarray) -> np.ndarray:
    """(k, n) or (k, 3, n) float64 C-contiguous per-cell ``values`` (n, k) or (n, k, 3) with the cell axis
    moved last; a view where the state came from ``FastAdvance`` (whose state arrays are views of
    cells-last arrays), a copy otherwise."""
    values = np.asarray(values)
    # .T, the cheaper call, moves axis 0 last where there are at most two axes
    moved = values.T if values.ndim <= 2 else values.transpose((*range(1, values.ndim), 0))
    return moved if moved.dtype == _FLOAT64 and moved.flags.c_contiguous else np.ascontiguousarray(moved, _FLOAT64)


def _freeze_numba_setup(compiled: bool) -> None:
    """After the first kernel ``_Compiled`` loads or compiles while a command runs
    (``warp_hcell.core.cli.running_command``): ``gc.freeze()``, every object alive then left out of later
    collections (``gc.collect()`` first where ``compiled``, so that the compiler's garbage is not kept).

    Numba's set-up at the first kernel of a process builds its typing and lowering registries, ~90 000 Python objects
    that live as long as the process and that every later full collection walked again. Frozen objects are
    still freed when their last reference goes; a reference cycle among them is never collected, so a library
    call (a notebook, a script) leaves the collector alone. Once per process; nothing where the process froze
    objects itself before."""
    global _NUMBA_SET_UP
    cli = sys.modules.get("warp_hcell.core.cli")  # only commands import it: no command without it
    if _NUMBA_SET_UP or cli is None or not cli.running_command():
        return
    _NUMBA_SET_UP = True
    if gc.get_freeze_count():
        return
    if compiled:
        gc.collect()
    gc.freeze()


_NUMBA_SET_UP = False
"""Whether ``_freeze_numba_setup`` froze (or found frozen) the objects of this process."""


class _Compiled:
    """A numba kernel called through the machine code compiled for the argument types of its first call.

    Numba's dispatcher types every argument at each call, a NamedTuple field by field in Python
    (~3-5 us for the tables ``features``, ``advance`` and ``moment_tangent`` take, of a ~80 us
    step). ``FastAdvance`` passes each argument with one fixed type (arrays of fixed dtype and
    rank, C-contiguous; scalars), so the entry point of the first call's signature serves every
    later call.

    Args:
        kernel: a numba dispatcher, or ``"module:name"``, imported on the first call (so that building a
            ``FastAdvance`` imports no numba).
    """

    def __init__(self, kernel) -> None:
        self._kernel = kernel
        self._entry = None

    @property
    def kernel(self):
        """The numba dispatcher (imported here the first time where ``kernel`` was a name)."""
        if isinstance(self._kernel, str):
            module, name = self._kernel.split(":")
            self._kernel = getattr(importlib.import_module(module), name)
        return self._kernel

    def __call__(self, *args):
        return self.entry(args)(*args)

    def entry(self, args: tuple):
        """The entry point (called with ``*args``) of the first call's signature, compiled or loaded for ``args``
        the first time."""
        if self._entry is None:
            kernel = self.kernel
            misses = sum(kernel.stats.cache_misses.values())
            self._entry = kernel.compile(tuple(kernel.typeof_pyval(a) for a in args))
            _freeze_numba_setup(sum(kernel.stats.cache_misses.values()) > misses)
        return self._entry


@dataclass(frozen=True)
class Kernels:
    """The compiled kernels of the cells of one dimension (``FastAdvance``).

    Each kernel is named ``"module:name"`` (``_Compiled`` imports it on first use).

    Attributes:
        features, advance: steps 1 and 3 (module docstring): ``training.fast_features.features`` and
            ``training.fast_increment.advance``, or ``training.fast_step3d.features3d`` and ``advance3d``.
        tangent: ``training.fast_tangent.moment_tangent``, or None where the network's tangent is not compiled.
        hold, newton, physics: the equilibrium corrections (the DEM's rest rule on the first guess, then the
            Newton steps: ``training.fast_equilibrium3d.hold_guess3d``, ``newton3d``) and the contact law
            after them (``training.fast_step3d.physics3d``), or None where the cells take none.
        balance_tangent: the tangent of a corrected increment (``fast_equilibrium3d.balance_tangent3d``), or None.
        step: features, perceptron, advance and branch counts in one call (``training.fast_increment.step``,
            ``training.fast_step3d.step3d``), or None.
        padded_features: whether ``features`` takes the features' scratch with more columns than cells
            (``Perceptron.padded_buffers``: the first layer then runs whole vectors too).
    """

    features: str
    advance: str
    tangent: str | None
    hold: str | None
    newton: str | None
    physics: str | None
    balance_tangent: str | None = None
    step: str | None = None
    padded_features: bool = False


_PLANAR, _SPATIAL, _STEP3D = "training.fast_increment", "training.fast_equilibrium3d", "training.fast_step3d"
KERNELS = {
    2: Kernels("training.fast_features:features", f"{_PLANAR}:advance", "training.fast_tangent:moment_tangent", None,
               None, None, step=f"{_PLANAR}:step", padded_features=True),
    3: Kernels(f"{_STEP3D}:features3d", f"{_STEP3D}:advance3d", None, f"{_SPATIAL}:hold_guess3d",
               f"{_SPATIAL}:newton3d", f"{_STEP3D}:physics3d", f"{_SPATIAL}:balance_tangent3d", step=f"{_STEP3D}:step3d"),
}
"""The compiled kernels of a cell by its dimension (a planar run imports none of the spatial ones, nor the reverse)."""


COMPACT_ROUNDS = (2, 2, 4)
"""The most Newton steps of the first rounds of ``FastAdvance``'s compacted corrections (the last round takes
the rest); each round runs on the cells the previous one left above the tolerance only."""


class FastIncrement(NamedTuple):
    """Outcome of ``FastAdvance.__call__`` (numpy, first axis n_cells).

    cell_size (n, dim) [m], free_position (n, n_free) [m], shear_force (n, n_pairs) [N] (spatial cells:
    (n, n_pairs, 3)): the new state (transposed views of cells-last arrays, so that the next increment
    reads them without a copy); moment (n, dim, dim) [N m] (compression positive); area (n,) [m^2]
    (spatial cells: the volume [m^3]); capped, opened:
    bool (n,), a Coulomb cap / the no-tension branch acted on some pair of the cell;
    mechanism: bool (n,), zero moment after the increment; relaxation_scaled: bool (n,),
    norm(d_eps) < ``RELAXATION_RAMP``; grains_held: int64 (n,), free grains held at rest
    (``training.cell_physics.hold_at_rest``).
    """

    cell_size: np.ndarray
    free_position: np.ndarray
    shear_force: np.ndarray
    moment: np.ndarray
    area: np.ndarray
    capped: np.ndarray
    opened: np.ndarray
    mechanism: np.ndarray
    relaxation_scaled: np.ndarray
    grains_held: np.ndarray


class Corrections(NamedTuple):
    """The equilibrium corrections of one ``FastAdvance`` call (``FastAdvance(corrections=K)``, spatial cells):
    force_ratio (2, n), the largest unbalanced free-DOF force over the largest normal force at the first
    guess and after the corrections (0 where not evaluated: no normal force, or a probe below the
    relaxation ramp), steps: int64 (n,), the Newton steps taken, and of them shortened: int64 (n,), those
    the line search shortened, and shifted: int64 (n,), those whose matrix was shifted (the step did no
    positive work along the unbalanced force; ``training.fast_equilibrium3d.newton3d``)."""

    force_ratio: np.ndarray
    steps: np.ndarray
    shortened: np.ndarray
    shifted: np.ndarray


class _Last(NamedTuple):
    """What ``FastAdvance.again_at_rest`` reads of this thread's last corrected ``increment`` (cells last):
    its state and probe, ``before`` and the first guess of the corrections (n_free, n) [m]."""

    size: np.ndarray
    free: np.ndarray
    shear: np.ndarray
    d_eps: np.ndarray
    before: Before
    guess: np.ndarray


class _Workspace(NamedTuple):
    """Scratch arrays of one ``FastAdvance`` call: ``before`` (``training.fast_tables.Before``, cells
    last), ``layers``, each perceptron layer's output (width, n padded: ``Perceptron.padded_buffers``) float32,
    ``counts`` (5,) int64 (``FastAdvance.last_counts``), and ``shapes``, those of the state (cells last) and probe
    that ``FastAdvance.increment`` takes."""

    before: Before
    layers: tuple
    counts: np.ndarray
    shapes: tuple


class FastAdvance:
    """``MesoNet.advance`` for inference on CPU: numba physics (float64) around the perceptron (float32).

    A cell's output does not depend on its batch or the CPU's vector width (``training.perceptron``);
    the arrays returned are new. Spatial cells run ``training.fast_step3d``.

    Args:
        net: the trained network, a ``MesoNet`` or its ``training.fast_model.NetArrays``; copied.
        corrections: the most exact Newton steps per cell-increment (spatial cells,
            ``fast_equilibrium3d.newton3d``; 0: none); ``last_corrections`` counts them.
        tolerance: force ratio [-] below which a cell is not corrected (None: the DEM's).
        guess: first guess of the corrections: ``"network"``, ``"still"`` or ``"affine"`` (``GUESSES``).
        halvings, shift: the most line-search halvings of a Newton step (0: full steps) and the first
            shift of a climbing step's matrix, a fraction of kn (None: ``fast_equilibrium3d``'s).
        compact: corrections in ``COMPACT_ROUNDS`` on the cells still above tolerance (same bits as False).
        precompiled: the fused step through ``training.precompiled`` (same bits as False); ``step_path``:
            "precompiled" (loaded by ``precompiled_loader``) or "numba" (why: ``precompiled_reason``)."""

    GUESSES = ("network", "still", "affine")
    """First guesses of the corrections: the network's, the free DOFs still, or following the cell's strain."""

    def __init__(self, net: NetArrays | Any, corrections: int = 0, tolerance: float | None = None,
                 guess: str = "network", halvings: int | None = None, shift: float | None = None,
                 compact: bool = True, precompiled: bool = True) -> None:
        net = net if isinstance(net, NetArrays) else arrays_of_net(net)
        schema = net.schema
        as_np = lambda a, dtype=np.float64: np.ascontiguousarray(a, dtype=dtype)  # noqa: E731
        frac = as_np(schema.driven_fraction)
        free_dofs = as_np(schema.free_dofs, np.int64)
        pairs = as_np(schema.pairs, np.int64)
        free_slot = np.full(frac.shape, -1, dtype=np.int64)
        free_slot[free_dofs[:, 0], free_dofs[:, 1]] = np.arange(free_dofs.shape[0])
        active_slot = np.full(pairs.shape[0], -1, dtype=np.int64)
        active_slot[as_np(net.active_index, np.int64)] = np.arange(int(net.active_index.shape[0]))
        self.cells = CellTables(frac, free_dofs, free_slot, pairs, as_np(schema.radius), as_np(schema.outer, np.int64),
                                active_slot)
        self.law = Physics(float(schema.diameter), float(schema.kn), float(schema.kt), float(schema.mu),
                           float(schema.contact_tolerance), float(GAP_CLIP), float(COMPLIANCE_SCALE),
                           float(RELAXATION_RAMP))
        self.scaling = Normalisation(as_np(net.feature_mean), as_np(net.feature_std), as_np(net.rate_mean),
                                     as_np(net.rate_std))
        self.perceptron = Perceptron([(as_np(weight), as_np(bias)) for weight, bias in net.layers])
        self._local = threading.local()
        self.dim = int(frac.shape[1])
        self._springs = (pairs.shape[0], *dimension(self.dim).spring_shape)
        kernels = KERNELS[self.dim]
        self._features = _Compiled(kernels.features)
        self._advance = _Compiled(kernels.advance)
        self._forward = _Compiled("training.perceptron:forward_layers")
        self._tangent = None if kernels.tangent is None else _Compiled(kernels.tangent)
        self._step = None if kernels.step is None else _Compiled(kernels.step)
        self._tables = (self.cells, self.law, self.scaling, self.perceptron.weight, self.perceptron.bias)
        self._step_entry = None
        self._precompiled = bool(precompiled)
        self.step_path: str | None = None
        self.precompiled_reason = self.precompiled_loader = ""
        self._padded_features = kernels.padded_features
        self._branch_counts = _Compiled(f"{_PLANAR}:branch_counts")
        if int(corrections) < 0 or (int(corrections) > 0 and kernels.newton is None):
            raise ValueError(f"corrections = {corrections}: equilibrium corrections are >= 0 and for spatial cells only")
        tolerance = DemSettings().force_tolerance if tolerance is None else tolerance
        if not tolerance > 0:
            raise ValueError(f"tolerance = {tolerance} must be > 0")
        if guess not in self.GUESSES or (guess != "network" and not corrections):
            raise ValueError(f"guess = {guess!r}: one of {', '.join(self.GUESSES)}, another than the network's with "
                             f"corrections only")
        self.corrections = int(corrections)
        self._fused = self._step is not None and not self.corrections
        self.guess = guess
        if self.corrections and (halvings is None or shift is None):
            from training.fast_equilibrium3d import HALVINGS, SHIFT  # noqa: PLC0415 (spatial kernels: imported on use)

            halvings, shift = HALVINGS if halvings is None else halvings, SHIFT if shift is None else shift
        halvings, shift = 0 if halvings is None else halvings, 0.0 if shift is None else shift  # unused without corrections
        if int(halvings) < 0:
            raise ValueError(f"halvings = {halvings} must be >= 0")
        self.halvings = int(halvings)
        if not shift >= 0:
            raise ValueError(f"shift = {shift} must be >= 0")
        self.shift = float(shift)
        self.tolerance = float(tolerance)
        self._displacement = _Compiled(f"{_PLANAR}:free_displacement")
        self._hold = None if kernels.hold is None else _Compiled(kernels.hold)
        self._newton = None if kernels.newton is None else _Compiled(kernels.newton)
        self.rounds = self._rounds(self.corrections, compact)
        self._physics = None if kernels.physics is None else _Compiled(kernels.physics)
        self._balance_tangent = (_Compiled(kernels.balance_tangent)
                                 if self.corrections and kernels.balance_tangent is not None else None)

    @property
    def has_tangent(self) -> bool:
        """Whether ``increment`` computes the tangent: planar cells, and spatial cells with corrections (the
        derivative of the balanced end state, ``fast_equilibrium3d.balance_tangent3d``)."""
        return self._tangent is not None or self._balance_tangent is not None

    @staticmethod
    def _rounds(corrections: int, compact: bool) -> tuple[int, ...]:
        """The most Newton steps of each round of the corrections (``COMPACT_ROUNDS`` up to ``corrections``)."""
        if not compact:
            return (corrections,) if corrections else ()
        rounds, left = [], corrections
        for cap in (*COMPACT_ROUNDS, corrections):
            if left > 0:
                rounds.append(min(cap, left))
                left -= rounds[-1]
        return tuple(rounds)

    def _corrected(self, size, free, shear, d_eps, d_free, before, ratios, steps, shortened, shifted) -> None:
        """The Newton steps (``fast_equilibrium3d.newton3d``) of the cells (cells last), in ``self.rounds``: after
        each round the cells that took all its steps and are still above the tolerance are gathered and the
        next round continues them alone; outputs written in place (``Corrections``)."""
        self._newton(size, free, shear, d_eps, d_free, self.cells, self.law, before, self.rounds[0], self.tolerance,
                     self.halvings, self.shift, ratios, steps, shortened, shifted)
        going = np.flatnonzero((steps == self.rounds[0]) & (ratios[1] > self.tolerance))
        for cap in self.rounds[1:]:
            if not going.size:
                return
            take = lambda a: np.take(a, going, axis=-1)  # noqa: E731 (C order; a[..., going] is not)
            part = Before(*(take(a) for a in before))
            sub_free = take(d_free)
            sub_ratios = np.empty((2, going.size))
            sub_counts = [np.empty(going.size, dtype=np.int64) for _ in range(3)]
            self._newton(take(size), take(free), take(shear), np.ascontiguousarray(d_eps[going]), sub_free, self.cells,
                         self.law, part, cap, self.tolerance, self.halvings, self.shift, sub_ratios, *sub_counts)
            d_free[:, going] = sub_free
            ratios[1, going] = sub_ratios[1]
            for whole, sub in zip((steps, shortened, shifted), sub_counts):
                whole[going] += sub
            going = going[(sub_counts[0] == cap) & (sub_ratios[1] > self.tolerance)]

    def _workspace(self, n: int) -> _Workspace:
        """This thread's scratch arrays for ``n`` cells (kept from its previous call with as many)."""
        work = getattr(self._local, "work", None)
        if work is None or work.before.m.shape[0] != n:
            n_free, n_pairs = self.cells.free_dofs.shape[0], self.cells.pairs.shape[0]
            columns = padded_cells(n) if self._padded_features else n
            before = Before(np.zeros((self.scaling.feature_mean.shape[0], columns), dtype=np.float32), np.empty(n),
                            np.empty((n_free, n)), np.empty((n_pairs, self.dim, n)),
                            np.empty((n_pairs, n), dtype=np.bool_),
                            np.empty((n_pairs, n)))
            work = _Workspace(before, self.perceptron.padded_buffers(n), np.empty(5, dtype=np.int64), self._shapes(n))
            self._local.work = work
        return work

    def _shapes(self, n: int) -> tuple:
        """The shapes of the state (cells last) and probe of ``n`` cells that ``increment`` takes."""
        return (self.dim, n), (self.cells.free_dofs.shape[0], n), (*self._springs, n), (n, self.dim)

    def _mlp_tangent(self, work: _Workspace, f_dot: np.ndarray) -> np.ndarray:
        """Derivative of the network output along d_eps_n and d_eps_t, (2, n_outputs, n) float32, from
        that of the probe features ``f_dot`` (2, 2, n) (features 0 and 1, the only ones that depend on
        d_eps) and the activations the forward pass left in ``work.layers``."""
        return np.stack([self.perceptron.jvp(0, f_dot[j], work.layers) for j in range(2)])

    def last_features(self) -> np.ndarray:
        """The z-scored float32 features of the states before this thread's last ``increment``,
        (n_features, n) cells last (a view of the scratch array: read it before the next call)."""
        before = self._local.work.before
        return before.feats[:, :before.m.shape[0]]

    def last_counts(self) -> np.ndarray:
        """The branch counts of this thread's last ``increment``, int64 (5,): its cells capped, opened, mechanism
        and relaxation-scaled (``FastIncrement``'s flags), and its grains held at rest, summed (this thread's
        scratch array: read it before the next call)."""
        return self._local.work.counts

    def last_corrections(self) -> Corrections | None:
        """The equilibrium corrections of this thread's last ``increment`` (None without corrections)."""
        return getattr(self._local, "corrections", None)

    def __call__(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                 d_eps: np.ndarray) -> FastIncrement:
        """One increment of every cell: state (n, dim), (n, n_free), (n, n_pairs) (spatial: (n, n_pairs, 3))
        and probe (n, dim) [-]."""
        return self.increment(cell_size, free_position, shear_force, d_eps)[0]

    def increment(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                  d_eps: np.ndarray, with_tangent: bool = False, held: np.ndarray | None = None
                  ) -> tuple[FastIncrement, np.ndarray | None]:
        """``__call__``, and with ``with_tangent`` also the consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t)
        [N m], (n, dim, dim), by forward-mode differentiation of the same increment (``training.fast_tangent``)
        or, with corrections, of its balanced end state (``fast_equilibrium3d.balance_tangent3d``); ValueError
        where ``has_tangent`` is False. ``held``: bool (n, n_free), free DOFs whose first
        guess of the corrections is no motion (with corrections only)."""
        dim = self.dim
        if with_tangent and not self.has_tangent:
            raise ValueError("the compiled tangent is planar, or of corrected spatial cells; take this one from torch autograd")
        size, free, shear = _cells_last(cell_size), _cells_last(free_position), _cells_last(shear_force)
        d_eps = np.ascontiguousarray(d_eps, _FLOAT64)
        n = size.shape[-1]
        shapes = (size.shape, free.shape, shear.shape, d_eps.shape)
        work = getattr(self._local, "work", None)
        if work is None or shapes != work.shapes:  # another number of cells, or shapes that do not fit
            if shapes != self._shapes(n):
                n_free, springs = self.cells.free_dofs.shape[0], self._springs
                raise ValueError(f"state shapes {cell_size.shape}, {free_position.shape}, {shear_force.shape} and "
                                 f"d_eps {d_eps.shape}: expected (n, {dim}), (n, {n_free}), "
                                 f"(n, {', '.join(map(str, springs))}), (n, {dim})")
            work = self._workspace(n)
        if held is not None and not self.corrections:
            raise ValueError("held: a first guess of the corrections, and this FastAdvance takes none")
        out = work.layers[-1]
        result = self._result(n)
        counts = work.counts
        fused = self._fused
        if fused:  # features, perceptron, advance and branch counts in one compiled call
            args = (size, free, shear, d_eps, *self._tables, work.before, work.layers, result, counts)
            step = self._step_entry
            if step is None:
                step = self._step_entry = self._fused_entry(args)
            step(args)
        else:
            self._features(size, free, shear, d_eps, self.cells, self.law, self.scaling, work.before)
            self._forward(self.perceptron.weight, self.perceptron.bias, work.before.feats, work.layers)
        if self.corrections:
            self._local.corrections = None
            self._local.last = None
            d_free = self._displacement(out, work.before.m, work.before.unbalanced, self.scaling, self.law)
            if self.guess == "still":
                d_free[:] = 0.0
            elif self.guess == "affine":
                d_free[:] = -free * d_eps.T[self.cells.free_dofs[:, 1]]
            self._hold(size, free, d_eps, d_free, self.cells, self.law, work.before)
            if held is not None:
                d_free[np.asarray(held, dtype=bool).T] = 0.0
            guess = d_free.copy()
            self._balance(size, free, shear, d_eps, d_free, work.before, result)
            self._local.last = _Last(size, free, shear, d_eps, work.before, guess)
        elif not fused:
            self._advance(size, free, shear, d_eps, out, self.cells, self.law, self.scaling, work.before, result)
        if not fused:
            self._branch_counts(result, counts)
        tangent = None
        if with_tangent and self._balance_tangent is not None:
            tangent = np.empty((n, dim, dim))
            self._balance_tangent(size, shear, result.new_size, result.new_free, result.held_dof, self.cells, self.law,
                                  work.before, tangent)
        elif with_tangent:
            from training.fast_tangent import probe_feature_tangent  # noqa: PLC0415 (numba: imported on first use)

            f_dot = np.empty((2, 2, n), dtype=np.float32)
            probe_feature_tangent(d_eps, work.before.m, self.scaling.feature_std, f_dot)
            tangent = np.empty((n, 2, 2))
            self._tangent(size, free, shear, d_eps, out, self._mlp_tangent(work, f_dot), self.cells, self.law,
                           self.scaling, work.before, result, tangent)
        return self._outcome(result), tangent

    def _fused_entry(self, args: tuple) -> Callable[[tuple], None]:
        """The fused step for ``args`` (its types serve every later call): precompiled where ``precompiled`` and it
        loads or builds (``training.precompiled.PrecompiledStep``), else numba's entry point; sets ``step_path``."""
        if self._precompiled:
            step = PrecompiledStep(args, kernel=KERNELS[self.dim].step)
            self.precompiled_reason, self.precompiled_loader = step.reason, step.loader
            if step.built:
                _freeze_numba_setup(True)
            if step.available:
                self.step_path = "precompiled"
                return step
        self.step_path = "numba"
        entry = self._step.entry(args)
        return lambda arguments: entry(*arguments)

    def _result(self, n: int) -> Advanced:
        """Empty ``Advanced`` arrays of ``n`` cells."""
        dim, n_free = self.dim, self.cells.free_dofs.shape[0]
        flags = np.empty((4, n), _BOOL)
        return Advanced(np.empty((dim, n)), np.empty((n_free, n)), np.empty((*self._springs, n)),
                        np.empty((n, dim, dim)), np.empty(n), flags[0], flags[1], flags[2], flags[3],  # *flags: slower
                        np.empty(n, _INT64), np.empty((n_free, n), _BOOL))

    @staticmethod
    def _outcome(result: Advanced) -> FastIncrement:
        """The ``FastIncrement`` of ``result`` (cells first, views)."""
        new_shear = result.new_shear
        last = new_shear.ndim - 1
        new_shear = new_shear.T if last == 1 else new_shear.transpose((last, *range(last)))  # .T: the cheaper call
        return FastIncrement(result.new_size.T, result.new_free.T, new_shear, result.moment, result.area, result.capped,
                             result.opened, result.mechanism, result.ramped, result.n_held)

    def _last_cells(self, index: np.ndarray, caller: str) -> tuple[tuple, _Last]:
        """((size, free, shear, d_eps, before), last): the cells ``index`` (int (m,)) of this thread's last corrected
        ``increment`` (cells last; ``before``'s features not gathered: read by no kernel after it), and that
        increment's ``_Last``; ValueError naming ``caller`` where there is none."""
        last = getattr(self._local, "last", None)
        if last is None:
            raise ValueError(f"{caller}: no corrected increment before it in this thread")
        take = lambda a: np.take(a, index, axis=-1)  # noqa: E731 (C order; a[..., index] is not)
        before = Before(last.before.feats, *map(take, last.before[1:]))
        return (take(last.size), take(last.free), take(last.shear), np.ascontiguousarray(last.d_eps[index]), before), last

    def again_at_rest(self, index: np.ndarray, held: np.ndarray) -> FastIncrement:
        """The cells ``index`` (int (m,)) of this thread's last corrected ``increment``, taken again with the free
        DOFs ``held`` (bool (m, n_free)) starting the corrections at rest: bit for bit those cells of
        ``increment(..., held=held)``, from the first guess of the last call (no features, no network);
        ``last_corrections`` then counts these corrections."""
        (size, free, shear, d_eps, before), last = self._last_cells(index, "again_at_rest")
        d_free = np.take(last.guess, index, axis=-1)
        d_free[np.asarray(held, dtype=bool).T] = 0.0
        result = self._result(d_eps.shape[0])
        self._balance(size, free, shear, d_eps, d_free, before, result)
        return self._outcome(result)

    def again_displaced(self, index: np.ndarray, d_free: np.ndarray) -> FastIncrement:
        """The cells ``index`` (int (m,)) of this thread's last corrected ``increment`` with the free-DOF
        displacement ``d_free`` (m, n_free) [m] as given: the rest rule and the contact law at those positions
        (no network, no corrections; ``last_corrections`` unchanged)."""
        (size, free, shear, d_eps, before), _ = self._last_cells(index, "again_displaced")
        result = self._result(d_eps.shape[0])
        self._physics(size, free, shear, d_eps, np.ascontiguousarray(np.asarray(d_free, dtype=np.float64).T),
                      self.cells, self.law, before, result)
        return self._outcome(result)

    def _balance(self, size, free, shear, d_eps, d_free, before: Before, result: Advanced) -> None:
        """The equilibrium corrections of the first guess ``d_free`` (n_free, n) [m] (in place), then the contact law
        at the corrected positions into ``result``; this thread's ``last_corrections`` then holds their counts."""
        n = d_eps.shape[0]
        ratios, steps = np.empty((2, n)), np.empty(n, dtype=np.int64)
        shortened, shifted = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
        self._corrected(size, free, shear, d_eps, d_free, before, ratios, steps, shortened, shifted)
        self._physics(size, free, shear, d_eps, d_free, self.cells, self.law, before, result)
        self._local.corrections = Corrections(ratios, steps, shortened, shifted)
