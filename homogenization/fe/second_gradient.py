"""Local second-gradient regularisation of the biaxial specimen (Chambon, Caillerie & Matsushima 2001).

``SecondGradientSpecimen(nx, ny, length=L, modulus=E_ref)`` is the ``BiaxialSpecimen`` (same
platens, pressure, programme, Newton loop) with three fields: the displacement u (8-node
serendipity quadrilaterals), the relaxed displacement gradient v_ij (bilinear, 4 components
11, 12, 21, 22, v_ij ~ d u_i / d x_j) and a Lagrange multiplier lambda_ij constant per element
that enforces v = grad u weakly (Matsushima, Chambon & Caillerie 2002). Virtual work, FE sign
(tension positive), for all (u*, v*, lambda*):

    int sigma : grad u* + D grad v . grad v* - lambda : (grad u* - v*) - lambda* : (grad u - v) dA
        = work of the lateral pressure and of the platen force,

sigma the Gauss-point stress of the first-gradient law (the homogenised H-model, fed
-sym grad u), and the isotropic elastic second-gradient law Sigma_ijk = D d v_ij / d x_k with
D = E_ref L^2 [N m], L the material length [m] and E_ref [N/m] the reference modulus
(``reference_modulus``). Where the strain is uniform, v = grad u, grad v = 0 and lambda = 0:
the first-gradient solution. All fields share the 2 x 2 Gauss points; the material sees only u.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skfem import Basis, BilinearForm, ElementQuad0, ElementQuad1, ElementQuadS2
from skfem.helpers import dot, grad

from homogenization.fe.solver import BiaxialSpecimen
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.core.parameters import FeDefaults

PENALTY_FACTOR = 1e4
"""beta / E_ref of the augmented-Lagrangian Newton step [-]."""
MAX_KRYLOV = 40
"""GMRES iterations allowed with the stored LU factors before the system is factorised afresh [-]."""
KRYLOV_RTOL = 1e-8
"""Relative residual of the preconditioned GMRES solve [-]."""
COMPONENTS = ((0, 0), (0, 1), (1, 0), (1, 1))
"""(i, j) of the components of v and lambda, in their order in the unknown vector."""


def _gradient_component(i: int, j: int) -> BilinearForm:
    @BilinearForm
    def form(lam, du, w):
        return du.grad[i, j] * lam
    return form


@BilinearForm
def _laplace(a, b, w):
    return dot(grad(a), grad(b))


@BilinearForm
def _mass(a, b, w):
    return a * b


class SecondGradientSpecimen(BiaxialSpecimen):
    """The biaxial specimen with the local second-gradient terms (module docstring).

    Args:
        nx, ny: elements across the width and along the height, each >= 1.
        length: material length L [m], > 0.
        modulus: reference modulus E_ref [N/m], > 0; D = E_ref L^2.
        width, height, newton_rtol, max_newton: as ``BiaxialSpecimen``.

    Unknowns x = (u, v_11, v_12, v_21, v_22, lambda_11, ..., lambda_22); the Newton test applies
    to the whole residual (its v and lambda parts are linear, solved exactly by each iteration).
    """

    def __init__(self, nx: int, ny: int, *, length: float, modulus: float, width: float = FeDefaults.width,
                 height: float = FeDefaults.height, newton_rtol: float = FeDefaults.newton_rtol,
                 max_newton: int = FeDefaults.max_newton, reuse_tangent: bool = False) -> None:
        if not (length > 0.0 and modulus > 0.0):
            raise ValueError(f"length and modulus must be > 0, got {length} and {modulus}")
        super().__init__(nx, ny, width=width, height=height, newton_rtol=newton_rtol, max_newton=max_newton,
                         element=ElementQuadS2(), reuse_tangent=reuse_tangent)
        self.length = float(length)
        quadrature = self.basis.quadrature
        self.v_basis = Basis(self.mesh, ElementQuad1(), quadrature=quadrature)
        self.l_basis = Basis(self.mesh, ElementQuad0(), quadrature=quadrature)
        nu, nv, nl = self.basis.N, self.v_basis.N, self.l_basis.N
        self.n_v, self.n_l = nv, nl
        c = len(COMPONENTS)
        self._G = sp.hstack([_gradient_component(i, j).assemble(self.l_basis, self.basis) for i, j in COMPONENTS])
        self._M = sp.kron(sp.identity(c), _mass.assemble(self.l_basis, self.v_basis))  # (c nv, c nl)
        self._lap = sp.kron(sp.identity(c), _laplace.assemble(self.v_basis))
        self._expand = sp.block_diag([self.tie, sp.identity(c * (nv + nl))], format="csr")
        self._areas = np.tile(_mass.assemble(self.l_basis).diagonal(), c)
        """Diagonal of the multiplier's mass matrix (element areas) [m^2], per multiplier unknown."""
        self._lu, self._lu_free = None, np.zeros(0, int)
        self.factorisations = 0
        """Sparse LU factorisations done by ``newton_correction`` so far."""
        self.krylov_iterations = 0
        """Preconditioned GMRES iterations done by ``newton_correction`` so far."""
        self.pivoted_factorisations = 0
        """Factorisations redone with partial pivoting (the pivot-free ones fell short) so far."""
        self.set_modulus(modulus)

    def set_modulus(self, modulus: float) -> None:
        """Set E_ref [N/m], > 0, hence D = E_ref L^2 [N m] (attributes ``modulus``, ``D``)."""
        if not modulus > 0.0:
            raise ValueError(f"modulus must be > 0, got {modulus}")
        self.modulus = float(modulus)
        self.D = self.modulus * self.length ** 2
        self.penalty = PENALTY_FACTOR * self.modulus
        """beta [N/m] of the augmented-Lagrangian Newton step (``newton_correction``)."""
        nu, c = self.basis.N, len(COMPONENTS)
        zero_uv = sp.csr_matrix((nu, c * self.n_v))
        self._linear = sp.bmat([[sp.csr_matrix((nu, nu)), zero_uv, -self._G],
                                [zero_uv.T, self.D * self._lap, self._M],
                                [-self._G.T, self._M.T, None]], format="csr")
        """Jacobian of the linear terms (second gradient and constraint), shape (n_unknowns, n_unknowns)."""

    @property
    def n_unknowns(self) -> int:
        return self.basis.N + len(COMPONENTS) * (self.n_v + self.n_l)

    @property
    def expand(self) -> sp.csr_matrix:
        return self._expand

    def system(self, x, stress, tangent):
        f_u, K_u = self._assemble(stress, tangent)
        n = self.basis.N
        f = self._linear @ x
        f[:n] += f_u
        if K_u is None:
            return f, None
        K = self._linear + sp.block_diag([K_u, sp.csr_matrix((x.size - n, x.size - n))], format="csr")
        return f, K

    def begin_step(self, fresh: bool) -> None:
        """Where ``fresh``, forget the stored LU factors: the steps from here on depend only on the
        state here, so a run resumed here repeats the uninterrupted run's arithmetic bit for bit."""
        if fresh:
            self._lu = None

    def newton_correction(self, K_r, residual, fixed):
        """Newton correction by an augmented-Lagrangian step (the multiplier block of the Jacobian,
        zero, replaced by -A / beta, A the multiplier's mass matrix, diagonal): the multiplier is
        condensed out element by element and the remaining (u, v) system is solved by GMRES
        preconditioned with the sparse LU factors of an earlier such system (``begin_step``),
        refactorised when GMRES needs more than ``MAX_KRYLOV`` iterations (or the fixed DOFs change). The residual
        stays exact, so the converged solution is that of the exact multiplier; the Jacobian's
        perturbation, of relative order E_ref / beta, only slows the final iterations. Counts:
        ``solver_counts``."""
        n = K_r.shape[0] - self._areas.size
        C = K_r[n:, :n]
        beta_over_area = self.penalty / self._areas
        K_p = (K_r[:n, :n] + C.T @ sp.diags(beta_over_area) @ C).tocsr()
        rhs = -residual[:n] - C.T @ (beta_over_area * residual[n:])
        free = np.setdiff1d(np.arange(n), fixed)
        A = K_p[free][:, free].tocsc()
        b = rhs[free]
        d_free = None
        if self._lu is not None and self._lu_free.size == free.size and np.array_equal(self._lu_free, free):
            count = [0]

            def counter(_):
                count[0] += 1

            precondition = spla.LinearOperator(A.shape, self._lu.solve)
            x, info = spla.gmres(A, b, M=precondition, rtol=KRYLOV_RTOL, atol=0.0, restart=MAX_KRYLOV,
                                 maxiter=1, callback=counter, callback_type="pr_norm")
            self.krylov_iterations += count[0]
            if info == 0:
                d_free = x
        if d_free is None:
            # symmetric ordering without pivoting: fast; GMRES checks what it gives
            self._lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
            self._lu_free = free
            self.factorisations += 1
            x, info = spla.gmres(A, b, M=spla.LinearOperator(A.shape, self._lu.solve), rtol=KRYLOV_RTOL, atol=0.0,
                                 restart=MAX_KRYLOV, maxiter=1)
            if info != 0:  # the pivot-free factors are not good enough: partial pivoting
                self.pivoted_factorisations += 1
                self._lu = spla.splu(A)
                x = self._lu.solve(b)
            d_free = x
        d_uv = np.zeros(n)
        d_uv[free] = d_free
        return np.concatenate([d_uv, beta_over_area * (C @ d_uv + residual[n:])])

    def solver_counts(self) -> dict[str, int]:
        """``factorisations``, ``pivoted_factorisations`` (the pivot-free factors fell short: a fallback) and
        ``krylov_iterations`` so far."""
        return {"factorisations": self.factorisations, "pivoted_factorisations": self.pivoted_factorisations,
                "krylov_iterations": self.krylov_iterations}

    def residual_weights(self, scale: float) -> np.ndarray:
        """1 for the displacement rows [N]; 1 / W for the v rows [N m]; scale / W for the lambda rows [m^2]."""
        c = len(COMPONENTS)
        return np.concatenate([np.ones(self.tie.shape[1]), np.full(c * self.n_v, 1.0 / self.width),
                               np.full(c * self.n_l, scale / self.width)])

    def gradient_of(self, x: np.ndarray) -> np.ndarray:
        """Nodal v_ij of the unknowns x, shape (4, n_vertices), components in ``COMPONENTS`` order."""
        n = self.basis.N
        return x[n:n + len(COMPONENTS) * self.n_v].reshape(len(COMPONENTS), self.n_v)

    def seed(self, isotropic_seed: float) -> np.ndarray:
        guess = super().seed(isotropic_seed)
        v = self.gradient_of(guess)
        v[0] = v[3] = -isotropic_seed
        return guess

    def axial_guess(self, x: np.ndarray, strain: float) -> np.ndarray:
        guess = super().axial_guess(x, strain)
        self.gradient_of(guess)[3] -= strain
        return guess


BAND_WIDTH_PER_LENGTH = 27.0
"""Band width / L [-] of the dense H-model specimen measured at L = 7.5 mm (docs/studies/bvp_second_gradient.md)."""
BAND_WIDTH_MEASURED_MAX = 0.2
"""Band width [m] below which the measured bands of L = 7.5 and 15 mm stay (0.204-0.206 and 0.228-0.230 m at
eps1 = 6 %): the width grows far less than L there (docs/studies/bvp_second_gradient.md)."""
LONGEST_MEASURED_LENGTH = 0.015
"""The longest L [m] whose band was measured."""


def expected_band_width(length: float) -> float:
    """The shear-band width [m] a mesh must resolve for the material length ``length`` [m]: BAND_WIDTH_PER_LENGTH x L,
    at most BAND_WIDTH_MEASURED_MAX up to LONGEST_MEASURED_LENGTH (the bands measured on the command's specimen are
    no narrower: 0.118 m at 3.75 mm, 0.204-0.230 m at 7.5 and 15 mm), beyond it growing from there in proportion
    to L (unmeasured)."""
    length = float(length)
    return min(BAND_WIDTH_PER_LENGTH * length,
               BAND_WIDTH_MEASURED_MAX * max(1.0, length / LONGEST_MEASURED_LENGTH))


def reference_modulus(material: HomogenisedMaterial, p0: float, n_steps: int = 20,
                      isotropic_seed: float = FeDefaults.isotropic_seed) -> float:
    """E_ref [N/m]: the shear modulus d sigma_12 / d gamma_12 of the material's first point at p0.

    The point (touching cells) is compressed isotropically (equal strains eps_11 = eps_22,
    gamma_12 = 0) until its mean stress (sigma_11 + sigma_22) / 2 reaches p0 [N/m], in
    ``n_steps`` equal steps of mean stress, each solved by Newton on the consistent tangent.

    Raises:
        ValueError: the material returns no tangent, or a step does not converge.
    """
    state = material.init_state()
    n = material.n_points
    e = np.full((n, 1), isotropic_seed) * np.array([1.0, 1.0, 0.0])
    state = material.update(state, e, with_tangent=False).state
    tangent = None
    for k in range(1, n_steps + 1):
        target = p0 * k / n_steps
        a = 0.0
        for _ in range(50):
            update = material.update(state, np.full((n, 1), a) * np.array([1.0, 1.0, 0.0]))
            p = 0.5 * (update.stress[0, 0] + update.stress[0, 1])
            if abs(p - target) <= 1e-10 * p0:
                break
            D = update.tangent[0]
            a += (target - p) / (0.5 * (D[0, 0] + D[0, 1] + D[1, 0] + D[1, 1]))
        else:
            raise ValueError(f"reference modulus: isotropic step {k} did not converge")
        state, tangent = update.state, update.tangent
    return float(tangent[0, 2, 2])
