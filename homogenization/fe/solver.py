"""Plane-strain biaxial specimen of the homogenised H-model, by finite elements (scikit-fem).

``BiaxialSpecimen(nx, ny)`` is a W x H rectangle of bilinear quadrilaterals (2 x 2 Gauss
points each, every Gauss point a material point of ``homogenization.material.homogenised``) between two
smooth rigid platens: the bottom platen holds u_y = 0, the top platen moves all top nodes by
one common u_y (a master degree of freedom), both leave u_x free (no friction); the bottom
node nearest x = W/2 holds u_x = 0 (no rigid-body drift). The lateral faces carry the
pressure p (traction -p n). ``run(material, programme)`` solves the programme step by step by
Newton's method with the consistent tangent of the material: scikit-fem assembles the
internal forces and the stiffness from the Gauss-point stresses and tangents and condenses
the prescribed degrees of freedom; each iteration is ONE batched material update of every
Gauss point.

Programme: ``isotropic_stage(p0, n)`` ramps the lateral pressure and the force of the top
platen together to p0 (stress control on both axes), ``shear_stage(eps, n)`` then moves the
top platen by eps H / n per step while the lateral pressure stays.

Frames and signs: x (index 0) is lateral, y (index 1) axial (the platen direction). The
material is fed and returns compression-positive Voigt quantities in the (x, y) frame
((eps_xx, eps_yy, gamma_xy), (sigma_xx, sigma_yy, sigma_xy)); scikit-fem works with
tension-positive displacements gradients: eps_c = -sym grad u, sigma_t = -sigma_c, same
tangent. Specimen averages (``StepResult``) use the biaxial convention: 1 = axial (y),
2 = lateral (x), compression positive: eps11 = -U_top / H, eps22 = -(u_x averaged over the right
face's length - the same on the left face) / W (the integral of the interpolated u_x), sigma11 = -(force of the top platen on the specimen) / W,
sigma22 and sigma12 = area averages of the Gauss-point sigma_xx and sigma_xy.
"""

from __future__ import annotations


from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from skfem import Basis, ElementQuad1, ElementVector, FacetBasis, LinearForm, MeshQuad, condense, solve
from skfem.helpers import dot

from homogenization.material.homogenised import HomogenisedMaterial, MaterialState
from warp_hcell.core.parameters import FeDefaults

QUADRATURE_ORDER = 2
"""Integration order of the bilinear quadrilaterals: 2 x 2 Gauss points [-]."""


REFRESH_EVERY = 10
"""Without checkpoints, solver data kept across steps (``begin_step``) is renewed every this many
steps; with checkpoints, every checkpoint interval, so that a resumed run repeats the arithmetic [-]."""
MAX_HALVINGS = 4
"""Halvings of a Newton correction after which it is taken even if the residual grew [-]."""
REUSE_CONTRACTION = 0.1
"""With ``reuse_tangent``, a Newton correction takes the kept stiffness where it is the step's first
or the previous correction cut the residual to at most this fraction [-]."""


class NewtonError(RuntimeError):
    """A load step did not converge (the message names the step and the residual)."""


@dataclass(frozen=True)
class LoadStep:
    """One load step: lateral pressure and either the force or the displacement of the top platen.

    Attributes:
        stage: stage label ("iso", "shear").
        pressure: lateral pressure at the end of the step [N/m], compression positive.
        platen_force: axial stress carried by the top platen [N/m] (force-controlled step), or None.
        platen_increment: top-platen displacement of the step, axial strain units
            (-delta U / H) [-], compression positive (displacement-controlled step), or None.
    """

    stage: str
    pressure: float
    platen_force: float | None = None
    platen_increment: float | None = None


def isotropic_stage(p0: float, n_steps: int) -> list[LoadStep]:
    """Lateral pressure and platen stress ramped together to p0 [N/m] in ``n_steps`` equal steps."""
    return [LoadStep("iso", p0 * k / n_steps, platen_force=p0 * k / n_steps) for k in range(1, n_steps + 1)]


def shear_stage(p0: float, eps_max: float, n_steps: int) -> list[LoadStep]:
    """Top platen moved by eps_max H in ``n_steps`` equal steps; lateral pressure p0 [N/m]."""
    return [LoadStep("shear", p0, platen_increment=eps_max / n_steps) for _ in range(n_steps)]


@dataclass
class StepResult:
    """Converged load step: specimen averages (1 = axial, 2 = lateral) and the fields.

    Attributes:
        stage: stage label.
        eps11, eps22: axial and lateral strain of the specimen [-], compression positive.
        sigma11, sigma22, sigma12: axial (platen), lateral and shear stress [N/m].
        iterations: Newton iterations (linear solves) of the step.
        residuals: out-of-balance force norm [N/m] before each iteration and at convergence.
        displacement: nodal displacement [m], shape (n_nodes, 2), (u_x, u_y), tension-positive FE sign.
        strain: Gauss-point strain (eps_xx, eps_yy, gamma_xy) [-], shape (n_points, 3), compression positive.
        stress: Gauss-point stress (sigma_xx, sigma_yy, sigma_xy) [N/m], shape (n_points, 3), compression positive.
        diagnostics: the backend's counts at the converged material update (``MaterialUpdate.diagnostics``)
            and the solver's (halvings, tangents, ``solver_counts``).
        opening: fabric-weighted mean opening angle of each Gauss point's cells [deg], shape
            (n_points,); NaN where the backend gives none.
        open_fraction: fraction of each Gauss point's contacts that are open [-], shape (n_points,).
    """

    stage: str
    eps11: float
    eps22: float
    sigma11: float
    sigma22: float
    sigma12: float
    iterations: int
    residuals: list[float]
    displacement: np.ndarray
    strain: np.ndarray
    stress: np.ndarray
    diagnostics: dict[str, float] = field(default_factory=dict)
    opening: np.ndarray | None = None
    open_fraction: np.ndarray | None = None


@LinearForm
def _outward_normal_load(v, w):
    """Work of a unit pressure: traction -n, so  -n . v."""
    return -dot(w.n, v)


class BiaxialSpecimen:
    """The meshed specimen, its boundary conditions and the Newton solver (module docstring).

    Args:
        nx, ny: elements across the width and along the height, each >= 1.
        width, height: specimen size W, H [m].
        newton_rtol: convergence when the out-of-balance force norm <= newton_rtol * scale * W [-].
        max_newton: Newton iterations allowed per load step.
        reuse_tangent: with a material that ``defers_tangent``, keep the last stiffness computed and
            correct with it across iterations and steps while it contracts (``REUSE_CONTRACTION``);
            a correction after a poorer one computes a fresh tangent (modified Newton). Counts:
            diagnostics ``tangents`` (computed) and ``tangents_reused``.
    """

    def __init__(self, nx: int, ny: int, *, width: float = FeDefaults.width, height: float = FeDefaults.height,
                 newton_rtol: float = FeDefaults.newton_rtol, max_newton: int = FeDefaults.max_newton,
                 element=None, reuse_tangent: bool = False) -> None:
        if int(nx) < 1 or int(ny) < 1:
            raise ValueError(f"element counts must be >= 1, got {nx} x {ny}")
        self.newton_rtol = float(newton_rtol)
        self.max_newton = int(max_newton)
        self.reuse_tangent = bool(reuse_tangent)
        self._kept_stiffness = None
        self.nx, self.ny = int(nx), int(ny)
        self.width, self.height = float(width), float(height)
        self.mesh = MeshQuad.init_tensor(np.linspace(0.0, width, nx + 1), np.linspace(0.0, height, ny + 1))
        element = ElementVector(ElementQuad1() if element is None else element)
        self.basis = Basis(self.mesh, element, intorder=QUADRATURE_ORDER)
        x, y = self.mesh.p
        nodal = self.basis.nodal_dofs
        self.x_dofs, self.y_dofs = self.basis.split_indices()
        """Displacement DOFs along x and along y (vertices and, for higher-order elements, the others)."""
        xd, yd = self.basis.doflocs[0], self.basis.doflocs[1]
        self.left_dofs = self.x_dofs[np.isclose(xd[self.x_dofs], 0.0)]
        self.right_dofs = self.x_dofs[np.isclose(xd[self.x_dofs], width)]
        bottom = np.flatnonzero(np.isclose(y, 0.0))
        pin = bottom[np.argmin(np.abs(x[bottom] - 0.5 * width))]
        lateral = self.mesh.facets_satisfying(lambda p: np.isclose(p[0], 0.0) | np.isclose(p[0], width))
        self.unit_pressure = _outward_normal_load.assemble(FacetBasis(self.mesh, element, facets=lateral,
                                                                      intorder=QUADRATURE_ORDER))
        # each lateral face's u_x averaged over its length: the nodes weighted by their shape functions' integrals
        self.face_weights = [np.abs(self.unit_pressure[d]) / np.abs(self.unit_pressure[d]).sum()
                             for d in (self.left_dofs, self.right_dofs)]
        # reduced unknowns: every DOF but the top u_y, which share one master DOF (the last)
        n = self.basis.N
        top_y = self.y_dofs[np.isclose(yd[self.y_dofs], height)]
        bottom_y = self.y_dofs[np.isclose(yd[self.y_dofs], 0.0)]
        keep = np.setdiff1d(np.arange(n), top_y)
        self.master = keep.size
        rows = np.concatenate([keep, top_y])
        cols = np.concatenate([np.arange(keep.size), np.full(top_y.size, self.master)])
        self.tie = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, keep.size + 1))
        """Sparse map u = tie @ a from the reduced unknowns a to all DOFs (rigid top platen)."""
        position = {dof: k for k, dof in enumerate(keep)}
        self.fixed = np.array([position[d] for d in bottom_y] + [position[nodal[0, pin]]])
        self.top_y = top_y
        self.n_points = self.mesh.nelements * self.basis.X.shape[1]
        self.weights = self.basis.dx.reshape(-1)
        """Gauss-point areas [m^2], shape (n_points,), point = element * n_gauss + gauss."""

    # -- fields ---------------------------------------------------------------------------
    def element_centroids(self) -> np.ndarray:
        """Element centres [m], shape (n_elements, 2)."""
        return self.mesh.p[:, self.mesh.t].mean(axis=1).T

    def points_per_element(self) -> int:
        """Gauss points per element."""
        return int(self.basis.X.shape[1])

    def strain(self, u: np.ndarray) -> np.ndarray:
        """Gauss-point strain (eps_xx, eps_yy, gamma_xy) [-], shape (n_points, 3), compression positive."""
        g = self.basis.interpolate(u).grad  # (2, 2, n_elements, n_gauss): g[i, j] = d u_i / d x_j
        return -np.stack([g[0, 0], g[1, 1], g[0, 1] + g[1, 0]], axis=-1).reshape(-1, 3)

    def _strain_operator(self) -> np.ndarray:
        """B [1/m], shape (n_elements, n_gauss, 3, n_local_dofs): tension-positive Voigt strain
        (eps_xx, eps_yy, gamma_xy) of each local displacement DOF at each Gauss point."""
        if getattr(self, "_B", None) is None:
            grads = np.stack([phi[0].grad for phi in self.basis.basis], axis=-1)  # (2, 2, ne, nq, nloc)
            self._B = np.ascontiguousarray(np.stack([grads[0, 0], grads[1, 1], grads[0, 1] + grads[1, 0]], axis=2))
            dofs = self.basis.element_dofs  # (nloc, ne)
            self._rows = np.repeat(dofs.T, dofs.shape[0], axis=1).ravel()
            self._cols = np.tile(dofs.T, (1, dofs.shape[0])).ravel()
        return self._B

    def _assemble(self, stress: np.ndarray, tangent: np.ndarray | None) -> tuple[np.ndarray, sp.csr_matrix | None]:
        """Internal forces and stiffness of the Gauss-point stresses and tangents, vectorised over
        elements: f = sum_q dx B^T sigma_t, K = sum_q dx B^T D B (sigma_t = -stress, same tangent);
        K is None where ``tangent`` is."""
        B = self._strain_operator()
        ne, nq = B.shape[:2]
        dx = self.basis.dx
        s = -stress.reshape(ne, nq, 3)
        f_e = np.einsum("eqak,eqa,eq->ek", B, s, dx)
        dofs = self.basis.element_dofs
        f_int = np.bincount(dofs.T.ravel(), f_e.ravel(), minlength=self.basis.N)
        if tangent is None:
            return f_int, None
        D = tangent.reshape(ne, nq, 3, 3)
        DB = np.einsum("eqab,eqbl->eqal", D, B)
        K_e = np.einsum("eqak,eqal,eq->ekl", B, DB, dx)
        K = sp.coo_matrix((K_e.ravel(), (self._rows, self._cols)), shape=(self.basis.N, self.basis.N)).tocsr()
        return f_int, K

    def averages(self, u: np.ndarray, f_int: np.ndarray, stress: np.ndarray) -> tuple[float, ...]:
        """(eps11, eps22, sigma11, sigma22, sigma12) of the specimen (1 = axial, 2 = lateral)."""
        U = u[self.top_y[0]]
        eps11 = -U / self.height
        left, right = self.face_weights
        eps22 = -(right @ u[self.right_dofs] - left @ u[self.left_dofs]) / self.width
        # force of the top platen on the specimen = internal force of the master DOF (< 0 in compression)
        sigma11 = -float(np.sum(f_int[self.top_y])) / self.width
        area = self.weights.sum()
        sigma22 = float(self.weights @ stress[:, 0]) / area
        sigma12 = float(self.weights @ stress[:, 2]) / area
        return eps11, eps22, sigma11, sigma22, sigma12

    # -- unknowns: the displacement here; a subclass adds fields after it ----------------------
    @property
    def n_unknowns(self) -> int:
        """Length of the full unknown vector x (here the displacement DOFs)."""
        return self.basis.N

    @property
    def expand(self) -> sp.csr_matrix:
        """Sparse map x = expand @ a from the reduced unknowns (the master DOF last of the displacement part)."""
        return self.tie

    def displacement_of(self, x: np.ndarray) -> np.ndarray:
        """The displacement DOFs of the full unknown vector x."""
        return x[:self.basis.N]

    def system(self, x: np.ndarray, stress: np.ndarray,
               tangent: np.ndarray | None) -> tuple[np.ndarray, sp.spmatrix | None]:
        """Internal force vector and its Jacobian (None where ``tangent`` is) for the unknowns x and the
        Gauss-point stress and tangent."""
        return self._assemble(stress, tangent)

    def begin_step(self, fresh: bool) -> None:
        """Called at the start of each load step's Newton iterations; ``fresh``: the run starts
        here or the step index is a multiple of the refresh interval (here nothing)."""

    def solver_counts(self) -> dict[str, int]:
        """The linear solver's counters so far, name -> count (here none); ``solve_step`` reports each step's
        increase of every one among its diagnostics."""
        return {}

    def newton_correction(self, K_r: sp.csr_matrix, residual: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """Correction of the reduced unknowns: K_r da = -residual with da = 0 at ``fixed`` (sparse LU)."""
        return solve(*condense(K_r, -residual, x=np.zeros(K_r.shape[0]), D=fixed))

    def residual_weights(self, scale: float) -> np.ndarray | float:
        """Factors turning each reduced residual component into a force [N] for the Newton test (here 1)."""
        return 1.0

    def seed(self, isotropic_seed: float) -> np.ndarray:
        """First guess of the first step: a homogeneous isotropic compression ``isotropic_seed`` [-]."""
        guess = np.zeros(self.n_unknowns)
        xd, yd = self.basis.doflocs
        guess[self.x_dofs] = -isotropic_seed * (xd[self.x_dofs] - 0.5 * self.width)
        guess[self.y_dofs] = -isotropic_seed * yd[self.y_dofs]
        return guess

    def axial_guess(self, x: np.ndarray, strain: float) -> np.ndarray:
        """x plus a homogeneous axial compression ``strain`` [-] (first guess of a new displacement stage)."""
        guess = x.copy()
        guess[self.y_dofs] -= strain * self.basis.doflocs[1][self.y_dofs]
        return guess

    # -- solution -------------------------------------------------------------------------
    def solve_step(self, material: HomogenisedMaterial, state: MaterialState, x_start: np.ndarray,
                   x_guess: np.ndarray, step: LoadStep, scale: float, where: str, fresh: bool = True):
        """Newton iterations of one load step from the converged unknowns ``x_start`` and ``state``.

        Where a correction increases the residual, it is halved (at most ``MAX_HALVINGS`` times,
        each costing an iteration); the count is the diagnostic ``line_search_halvings``, and
        ``growths_taken`` counts the iterates taken after ``MAX_HALVINGS`` halvings though the residual grew. Where the
        material ``defers_tangent``, an update computes its tangent only when a correction needs it
        (not for the converged iterate, nor a halving; with ``reuse_tangent`` only where the kept
        stiffness stopped contracting); the counts are ``tangents`` and ``tangents_reused``. The step's
        increase of each of ``solver_counts`` is a diagnostic of that name. Where ``fresh``, the kept stiffness is
        dropped (a resumed run repeats the arithmetic).

        Returns (x, material update, internal force vector, iterations, residual norms, diagnostics).
        """
        expand = self.expand
        self.begin_step(fresh)
        x = x_guess.copy()
        fixed = self.fixed
        if step.platen_increment is not None:
            x[self.top_y] = x_start[self.top_y[0]] - step.platen_increment * self.height
            fixed = np.append(fixed, self.master)
        load = np.zeros(self.n_unknowns)
        load[:self.basis.N] = step.pressure * self.unit_pressure
        f_ext = expand.T @ load
        if step.platen_force is not None:
            f_ext[self.master] -= step.platen_force * self.width
        eps_start = self.strain(self.displacement_of(x_start))
        residuals: list[float] = []
        free = np.setdiff1d(np.arange(expand.shape[1]), fixed)
        accepted, step_x, alpha, halvings, tangents, reused, grown = np.inf, None, 1.0, 0, 0, 0, 0
        counts = self.solver_counts()
        defer = material.defers_tangent
        if fresh:
            self._kept_stiffness = None
        for iteration in range(self.max_newton + 1):
            d_e = self.strain(self.displacement_of(x)) - eps_start
            update = material.update(state, d_e, with_tangent=not defer)
            tangents += not defer
            f_int, K = self.system(x, update.stress, update.tangent)
            residual = expand.T @ f_int - f_ext
            norm = float(np.linalg.norm((residual * self.residual_weights(scale))[free]))
            residuals.append(norm / self.width)
            if norm <= self.newton_rtol * scale * self.width:
                totals = {name: float(value) for name, value in update.diagnostics.items()}
                totals["line_search_halvings"] = float(halvings)
                totals["growths_taken"] = float(grown)
                totals["tangents"] = float(tangents)
                totals["tangents_reused"] = float(reused)
                totals.update({name: float(value - counts[name]) for name, value in self.solver_counts().items()})
                return x, update, f_int, iteration, residuals, totals
            if iteration == self.max_newton:
                break
            if norm > accepted and alpha > 1.0 / 2 ** MAX_HALVINGS:
                # the residual grew (e.g. contacts switching back and forth): halve the last correction
                alpha *= 0.5
                halvings += 1
                x = x_base + alpha * step_x
                continue
            grown += norm > accepted  # halved MAX_HALVINGS times and still grown: taken all the same
            kept = self._kept_stiffness
            if K is None and kept is not None and (step_x is None or norm <= REUSE_CONTRACTION * accepted):
                K = kept
                reused += 1
            elif K is None:
                _, K = self.system(x, update.stress, material.tangent(state, d_e, update))
                tangents += 1
                self._kept_stiffness = K if self.reuse_tangent else None
            K_r = (expand.T @ K @ expand).tocsr()
            accepted, alpha, x_base = norm, 1.0, x
            step_x = expand @ self.newton_correction(K_r, residual, fixed)
            x = x + step_x
        raise NewtonError(f"{where}: Newton did not converge in {self.max_newton} iterations "
                          f"(out-of-balance {residuals[-1]:.3g} N/m, tolerance {self.newton_rtol * scale:.3g} N/m)")

    def run(self, material: HomogenisedMaterial, steps: list[LoadStep], *, scale: float,
            isotropic_seed: float = FeDefaults.isotropic_seed, progress=None,
            checkpoint=None) -> list[StepResult]:
        """Solve the load steps in order; returns one ``StepResult`` per step.

        Args:
            material: a ``HomogenisedMaterial`` with ``n_points`` = this specimen's Gauss points.
            steps: the load steps (``isotropic_stage`` + ``shear_stage``).
            scale: stress scale of the convergence test (p0) [N/m].
            isotropic_seed: homogeneous isotropic strain of the first Newton guess [-] (the
                touching, force-free cells have no stiffness; a small compression closes them).
            progress: optional callable(step_index, StepResult) called after each converged step.
            checkpoint: optional ``homogenization.fe.checkpoint.Checkpoint``: the run starts from
                its saved step where it holds one, and saves every ``checkpoint.every`` steps.

        The full unknown vector of the last converged step is left in ``last_unknowns``.
        """
        if material.n_points != self.n_points:
            raise ValueError(f"material has {material.n_points} points, the mesh {self.n_points} Gauss points")
        state = material.init_state()
        x = np.zeros(self.n_unknowns)
        previous = np.zeros_like(x)
        results: list[StepResult] = []
        if checkpoint is not None and checkpoint.exists():
            x, previous, state, results = checkpoint.load(material, len(steps))
        nodal = self.basis.nodal_dofs
        first = len(results)
        refresh = checkpoint.every if checkpoint is not None else REFRESH_EVERY
        for k in range(first, len(steps)):
            step = steps[k]
            if k == 0:
                guess = self.seed(isotropic_seed)
            elif step.stage != steps[k - 1].stage and step.platen_increment is not None:
                guess = self.axial_guess(x, step.platen_increment)
            else:
                guess = x + (x - previous)  # the last step's increment again
            where = f"step {k + 1} ({step.stage})"
            x_new, update, f_int, iterations, residuals, totals = self.solve_step(
                material, state, x, guess, step, scale, where, fresh=k == first or k % refresh == 0)
            previous, x, state = x, x_new, update.state
            self.last_unknowns = x
            u = self.displacement_of(x)
            eps11, eps22, sigma11, sigma22, sigma12 = self.averages(u, f_int, update.stress)
            opening, open_fraction = point_observables(material, state)
            results.append(StepResult(step.stage, eps11, eps22, sigma11, sigma22, sigma12, iterations, residuals,
                                      np.stack([u[nodal[0]], u[nodal[1]]], axis=1), state.strain.copy(),
                                      update.stress.copy(), totals, opening, open_fraction))
            if checkpoint is not None and ((k + 1) % checkpoint.every == 0 or k + 1 == len(steps)):
                checkpoint.save(x, previous, material, state, results)
            if progress is not None:
                progress(k, results[-1])
        return results


def point_observables(material: HomogenisedMaterial, state: MaterialState) -> tuple[np.ndarray, np.ndarray]:
    """Per Gauss point: fabric-weighted mean opening angle [deg] and fraction of open contacts [-].

    Uses the backend's ``observables`` ``alpha_deg``, ``closed1``, ``closed2`` (an H-cell has four
    type-1 and two type-2 contacts); NaN, shape (n_points,), where the backend does not give them.
    """
    nan = np.full(material.n_points, np.nan)
    try:
        obs = material.model.observables(state.cells)
    except (AttributeError, NotImplementedError):
        return nan, nan.copy()
    if not {"alpha_deg", "closed1", "closed2"} <= set(obs):
        return nan, nan.copy()
    n = material.orient.n_cells
    w = material.orient.weights / material.orient.weights.sum()
    alpha = np.asarray(obs["alpha_deg"], float).reshape(material.n_points, n) @ w
    open_ = (4.0 * (1.0 - np.asarray(obs["closed1"], float)) + 2.0 * (1.0 - np.asarray(obs["closed2"], float))) / 6.0
    return alpha, open_.reshape(material.n_points, n) @ w
