"""Reference finite-strain solver on quadratic tetrahedra, for verifying `fem.engine.assembly`.

The same decoupled neo-Hookean law as the production engine (`fem.engine.material`),

    psi(F) = mu/2 (J^(-2/3) I1 - 3) + K/2 (J - 1)^2,

discretised with scikit-fem in one of two ways:

``"taylor-hood"`` (default)
    P2 displacement, continuous P1 pressure: the stationary points of the perturbed-Lagrangian
    potential

        Pi(u, p) = int [psi_iso(F) + p (J - 1) - p^2 / (2 K)] dV - int b . u dV,

    whose pressure equation gives ``p = K (J - 1)`` in the weak (P1-projected) sense. The pair
    is inf-sup stable, so it does not lock however close ``nu`` is to 1/2.
``"p2"``
    Pure P2 displacement with the pointwise volumetric energy ``K/2 (J - 1)^2``: more accurate
    than P1 but not locking-free in principle; kept to show how much it locks at nu = 0.495.

Newton's method solves the (symmetric, for Taylor-Hood indefinite) system with a sparse LU
factorization, reused as GMRES preconditioner while it stays good (`LinearSolver`), under a
load ramp with cutbacks. The residual, the body force and the pressure
blocks are scikit-fem ``LinearForm``/``BilinearForm`` assemblies; the displacement block of
the tangent, ``int grad(v) : A : grad(du) dV`` with the material tangent ``A``, is assembled by
batched products of the same basis data (`stiffness_uu`), because scikit-fem's form loop
over the 30 x 30 local basis pairs of a vector P2 tetrahedron takes minutes on the finest
benchmark mesh; `stiffness_form` is the plain ``BilinearForm`` it is tested against.

Units: mm and Pa; body forces in Pa/mm (force per reference volume), nodal forces in
Pa mm^2 = 1e-6 N, energies in Pa mm^3 = 1e-9 J. Degrees of freedom follow scikit-fem's
``ElementVector(ElementTetP2())`` numbering, which is ``3 * scalar_dof + component`` with the
mesh vertices as the first scalar DOFs and the edge midpoints after them; displacements are
therefore returned as ``(N_nodes, 3)`` arrays whose first rows are the mesh vertices.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import skfem
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.sparse.linalg import LinearOperator, gmres, splu

from fem.contract.quality import signed_volume
from fem.engine.material import isochoric_pk1, isochoric_tangent

FORMULATIONS = ("taylor-hood", "p2")


class ReferenceSolverError(RuntimeError):
    """Newton or the load ramp of the reference solver failed."""


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def hemisphere(radius: float = 50.0, level: int = 0, half: bool = False) -> skfem.MeshTet:
    """A hemisphere of tetrahedra on the plane z = 0, apex at ``(0, 0, radius)``.

    The base mesh is the upper half of ``MeshTet.init_ball(2)`` (256 tetrahedra, 85 vertices,
    its boundary projected onto the sphere); each ``level`` refines every tetrahedron into
    eight *without* moving the boundary, so all levels mesh exactly the same polyhedron
    (nested meshes: the discretisation error is measured on a fixed domain).

    Parameters
    ----------
    radius : float
        Radius of the sphere the base vertices lie on, mm.
    level : int
        Number of uniform refinements.
    half : bool
        Keep only the half x >= 0 (a quarter ball, 128 base tetrahedra): with a load in the
        symmetry plane x = 0, that plane then carries the symmetry condition ``u_x = 0``.

    Returns
    -------
    skfem.MeshTet
        Vertex coordinates in mm; the flat face lies on z = 0, the body in z >= 0.
    """
    ball = skfem.MeshTet.init_ball(2)
    centroids = ball.p[:, ball.t].mean(axis=1)
    upper = (centroids[2] > 0) & ((centroids[0] > 0) if half else True)
    t = ball.t[:, upper]
    used = np.unique(t)
    renumber = np.full(ball.p.shape[1], -1)
    renumber[used] = np.arange(len(used))
    mesh = skfem.MeshTet(radius * ball.p[:, used], renumber[t])
    return mesh.refined(level) if level > 0 else mesh


def oriented_cells(mesh: skfem.MeshTet) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points ``(N, 3)`` (mm) and cells ``(E, 4)`` of ``mesh`` with every cell positively
    oriented (`fem.contract.quality.signed_volume` > 0), as `fem.engine.assembly.HyperelasticBody` needs."""
    points = np.ascontiguousarray(mesh.p.T, dtype=float)
    cells = np.ascontiguousarray(mesh.t.T, dtype=np.int64)
    negative = signed_volume(points, cells) < 0
    cells[negative] = cells[negative][:, [0, 2, 1, 3]]
    return points, cells


# --------------------------------------------------------------------------------------------
# Discretisation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Discretization:
    """Bases and material of a reference problem.

    Attributes
    ----------
    mesh : skfem.MeshTet
        Reference configuration, mm.
    mu, kappa : float
        Shear and bulk modulus, Pa (homogeneous).
    formulation : {"taylor-hood", "p2"}
    basis_u : skfem.CellBasis
        ``ElementVector(ElementTetP2())``, N_u = 3 N_nodes DOFs.
    basis_s : skfem.CellBasis
        The scalar P2 basis on the same quadrature (its gradients feed `stiffness_uu`).
    basis_p : skfem.CellBasis or None
        P1 pressure (Taylor-Hood only), N_p = number of vertices.
    """

    mesh: skfem.MeshTet
    mu: float
    kappa: float
    formulation: str
    basis_u: skfem.CellBasis
    basis_s: skfem.CellBasis
    basis_p: skfem.CellBasis | None

    @property
    def n_u(self) -> int:
        return self.basis_u.N

    @property
    def n_p(self) -> int:
        return 0 if self.basis_p is None else self.basis_p.N

    @property
    def n_nodes(self) -> int:
        return self.basis_s.N


def discretize(
    mesh: skfem.MeshTet,
    mu: float,
    kappa: float,
    formulation: str = "taylor-hood",
    intorder: int = 4,
) -> Discretization:
    """Bases on ``mesh`` for the chosen formulation (quadrature of ``intorder``, default 4:
    11 points per tetrahedron)."""
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
    basis_u = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP2()), intorder=intorder)
    basis_s = basis_u.with_element(skfem.ElementTetP2())
    local = np.arange(basis_u.Nbfun)
    if not np.array_equal(
        basis_u.element_dofs, 3 * basis_s.element_dofs[local // 3] + (local % 3)[:, None]
    ):  # the vector DOF layout `stiffness_uu` and the (N, 3) arrays rely on
        raise RuntimeError("unexpected DOF layout of ElementVector(ElementTetP2())")
    basis_p = basis_u.with_element(skfem.ElementTetP1()) if formulation == "taylor-hood" else None
    return Discretization(mesh, float(mu), float(kappa), formulation, basis_u, basis_s, basis_p)


def dofs_where(
    disc: Discretization,
    marker: Callable[[NDArray], NDArray],
    components: Sequence[int] = (0, 1, 2),
) -> NDArray[np.int64]:
    """Displacement DOFs of the given components at the nodes (vertices and edge midpoints)
    whose coordinates ``x`` (3, n), mm, satisfy ``marker(x)``; sorted indices into the N_u
    displacement DOFs."""
    nodes = np.flatnonzero(marker(disc.basis_s.doflocs))
    return np.sort((3 * nodes[:, None] + np.asarray(components)[None, :]).ravel())


# --------------------------------------------------------------------------------------------
# Material state at the quadrature points
# --------------------------------------------------------------------------------------------


def deformation_gradient(disc: Discretization, u: NDArray) -> NDArray[np.float64]:
    """``F = I + grad u`` at the quadrature points, shape (E, Q, 3, 3), for the displacement
    DOF vector ``u`` (N_u,), mm."""
    grad = disc.basis_u.interpolate(u).grad  # (3, 3, E, Q)
    return np.eye(3) + np.moveaxis(grad, (0, 1), (-2, -1))


def jacobian_second_derivative(F: NDArray) -> NDArray[np.float64]:
    """``d2 J / dF_ij dF_kl = J (F^-T_ij F^-T_kl - F^-1_jk F^-1_li)``, shape (..., 3, 3, 3, 3)."""
    J = np.linalg.det(F)[..., None, None, None, None]
    Finv = np.linalg.inv(F)
    FinvT = np.swapaxes(Finv, -1, -2)
    return J * (
        np.einsum("...ij,...kl->...ijkl", FinvT, FinvT)
        - np.einsum("...jk,...li->...ijkl", Finv, Finv)
    )


@dataclass(frozen=True)
class MaterialState:
    """Kinematics and stresses at the quadrature points, all with leading shape (E, Q).

    Attributes
    ----------
    J : (E, Q)
        ``det F``.
    cofactor : (E, Q, 3, 3)
        ``dJ/dF = J F^-T``, mm^0.
    pressure : (E, Q)
        ``p``: the interpolated P1 pressure (Taylor-Hood) or ``K (J - 1)`` (P2), Pa.
    stress : (E, Q, 3, 3)
        First Piola-Kirchhoff stress ``P_iso + p J F^-T``, Pa.
    tangent : (E, Q, 3, 3, 3, 3) or None
        ``dP/dF`` at fixed pressure (Taylor-Hood) or the full ``d2 psi / dF2`` (P2), Pa.
    """

    J: NDArray
    cofactor: NDArray
    pressure: NDArray
    stress: NDArray
    tangent: NDArray | None


def material_state(
    disc: Discretization, u: NDArray, p: NDArray | None, with_tangent: bool = True
) -> MaterialState:
    """Evaluate the constitutive law at the quadrature points for DOF vectors ``u`` (N_u,),
    mm, and ``p`` (N_p,), Pa (ignored by the P2 formulation); ``with_tangent=False`` leaves
    ``tangent`` None (line-search trials need only the stress)."""
    F = deformation_gradient(disc, u)
    J = np.linalg.det(F)
    cofactor = J[..., None, None] * np.swapaxes(np.linalg.inv(F), -1, -2)
    if disc.formulation == "taylor-hood":
        pressure = np.asarray(disc.basis_p.interpolate(p))
    else:
        pressure = disc.kappa * (J - 1.0)
    stress = isochoric_pk1(F, disc.mu) + pressure[..., None, None] * cofactor
    if not with_tangent:
        return MaterialState(J, cofactor, pressure, stress, None)
    tangent = isochoric_tangent(F, disc.mu) + pressure[
        ..., None, None, None, None
    ] * jacobian_second_derivative(F)
    if disc.formulation == "p2":  # U''(J) dJ/dF (x) dJ/dF
        tangent = tangent + disc.kappa * np.einsum("...ij,...kl->...ijkl", cofactor, cofactor)
    return MaterialState(J, cofactor, pressure, stress, tangent)


def _to_skfem(a: NDArray, tensor_rank: int) -> NDArray:
    """Move the trailing tensor axes of an (E, Q, ...) array to the front, skfem's layout."""
    n = a.ndim
    return np.moveaxis(a, range(n - tensor_rank, n), range(tensor_rank))


# --------------------------------------------------------------------------------------------
# Forms
# --------------------------------------------------------------------------------------------


@skfem.LinearForm
def stress_form(v, w):
    """``int P : grad v dV``: internal forces, Pa mm^2."""
    return np.einsum("ij...,ij...->...", w["P"], v.grad)


@skfem.LinearForm
def body_force_form(v, w):
    """``int b . v dV`` for a constant body force ``b`` (3,), Pa/mm."""
    b = w["b"]
    return b[0] * v[0] + b[1] * v[1] + b[2] * v[2]


@skfem.LinearForm
def constraint_form(q, w):
    """``int (J - 1 - p / K) q dV``: the weak pressure equation, mm^3."""
    return (w["J"] - 1.0 - w["p"] / w["kappa"]) * q


@skfem.BilinearForm
def coupling_form(dp, v, w):
    """``int dp (J F^-T : grad v) dV``: the displacement-pressure block, mm^2."""
    return dp * np.einsum("ij...,ij...->...", w["cofactor"], v.grad)


@skfem.BilinearForm
def pressure_mass_form(dp, q, w):
    """``int dp q dV``, mm^3."""
    return dp * q


@skfem.BilinearForm
def stiffness_form(du, v, w):
    """``int grad v : A : grad du dV``: the displacement block, Pa mm (slow reference of
    `stiffness_uu`)."""
    return np.einsum("ijkl...,kl...,ij...->...", w["A"], du.grad, v.grad)


def stiffness_uu(disc: Discretization, tangent: NDArray) -> sparse.csr_matrix:
    """``int grad v : A : grad du dV`` (N_u, N_u), Pa mm, by batched products.

    With the scalar P2 gradients ``G[e, q, a, j]`` and the quadrature weights ``dx[e, q]``, the
    element block is ``K[e, a, i, b, k] = sum_q dx G[a, j] A[i, j, k, l] G[b, l]`` and its
    local index ``3 a + i`` is that of `discretize`'s vector basis.

    Parameters
    ----------
    tangent : (E, Q, 3, 3, 3, 3)
        Material tangent ``A = dP/dF`` at the quadrature points, Pa.
    """
    basis = disc.basis_s
    n_el, n_qp = basis.dx.shape
    n_loc = basis.Nbfun
    grads = np.stack([basis.basis[a][0].grad for a in range(n_loc)])  # (a, j, E, Q)
    grads = np.moveaxis(grads, (2, 3), (0, 1))  # (E, Q, a, j)
    Ke = np.zeros((n_el, n_loc, 3, n_loc, 3))
    for q in range(n_qp):
        G = grads[:, q]
        AG = np.einsum("eijkl,ebl->eijkb", tangent[:, q], G)
        Ke += basis.dx[:, q, None, None, None, None] * np.einsum("eaj,eijkb->eaibk", G, AG)
    dofs = disc.basis_u.element_dofs.T  # (E, 3 n_loc)
    size = 3 * n_loc
    rows = np.repeat(dofs, size, axis=1).ravel()
    cols = np.tile(dofs, (1, size)).ravel()
    return sparse.coo_matrix(
        (Ke.reshape(n_el, size * size).ravel(), (rows, cols)), shape=(disc.n_u, disc.n_u)
    ).tocsr()


def body_force_vector(disc: Discretization, force_density: ArrayLike) -> NDArray[np.float64]:
    """Consistent nodal forces (N_u,), Pa mm^2, of a constant body force (3,), Pa/mm."""
    return body_force_form.assemble(disc.basis_u, b=tuple(float(c) for c in force_density))


def residual(
    disc: Discretization, state: MaterialState, p: NDArray | None, f_ext: NDArray
) -> NDArray[np.float64]:
    """``[f_int - f_ext (N_u,), pressure equation (N_p,)]``; zero at equilibrium."""
    r_u = stress_form.assemble(disc.basis_u, P=_to_skfem(state.stress, 2)) - f_ext
    if disc.basis_p is None:
        return r_u
    r_p = constraint_form.assemble(
        disc.basis_p, J=state.J, p=np.asarray(disc.basis_p.interpolate(p)), kappa=disc.kappa
    )
    return np.concatenate([r_u, r_p])


def tangent_matrix(disc: Discretization, state: MaterialState) -> sparse.csr_matrix:
    """Jacobian of `residual`: ``K_uu`` (P2), or ``[[K_uu, K_up], [K_up^T, -M_p / K]]``
    (Taylor-Hood, symmetric indefinite)."""
    K_uu = stiffness_uu(disc, state.tangent)
    if disc.basis_p is None:
        return K_uu
    K_up = coupling_form.assemble(disc.basis_p, disc.basis_u, cofactor=_to_skfem(state.cofactor, 2))
    M_p = pressure_mass_form.assemble(disc.basis_p)
    return sparse.bmat([[K_uu, K_up], [K_up.T, -M_p / disc.kappa]], format="csr")


# --------------------------------------------------------------------------------------------
# Newton and the load ramp
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceSettings:
    """Newton and load-ramp settings.

    Parameters
    ----------
    tolerance : float
        Converged when the free displacement residual is below ``tolerance`` times the norm
        of the internal forces (reactions included) or of the external forces, and the
        pressure residual below ``tolerance`` times the body volume.
    max_iterations : int
        Newton iterations per load increment.
    max_increment : float
        Largest load-factor increment.
    max_cutbacks : int
        Halvings of a failed increment before giving up.
    step_tolerance : float
        ... or when a Newton correction moves no displacement DOF by more than this, mm (the
        residual of a tiny load can sit at its round-off floor above ``tolerance``).
    min_jacobian : float
        Smallest admissible ``det F`` at a quadrature point in the line search.
    """

    tolerance: float = 1e-9
    step_tolerance: float = 1e-12
    max_iterations: int = 20
    max_increment: float = 0.25
    max_cutbacks: int = 8
    min_jacobian: float = 1e-2


@dataclass(frozen=True)
class ReferenceSolution:
    """Equilibria at the recorded load factors.

    Attributes
    ----------
    disc : Discretization
    load_factors : (R,)
    displacement : (R, N_nodes, 3)
        Nodal displacements, mm (vertices first, then edge midpoints).
    pressure : (R, N_p) or None
        Nodal pressures, Pa (Taylor-Hood).
    newton_iterations : int
        Total Newton iterations of the ramp.
    factorizations : int
        Sparse LU factorizations of the ramp.
    """

    disc: Discretization
    load_factors: NDArray
    displacement: NDArray
    pressure: NDArray | None
    newton_iterations: int
    factorizations: int


class LinearSolver:
    """Solves the Newton systems with one sparse LU reused across iterations and increments.

    The stored factorization preconditions GMRES on the current tangent; once GMRES needs more
    than half of ``max_iterations`` iterations (or fails) the next solve factorizes afresh. The factorization
    does not pivot (``DiagPivotThresh = 0``, symmetric minimum-degree ordering): the
    Taylor-Hood tangent is quasi-definite (positive-definite displacement block, negative
    definite pressure block) and so factorizable in any symmetric order; should GMRES still
    fail, a pivoting factorization solves the system directly.
    """

    def __init__(self, rtol: float = 1e-8, max_iterations: int = 30) -> None:
        self.rtol, self.max_iterations = rtol, max_iterations
        self.lu = None
        self.factorizations = 0

    def _gmres(self, K: sparse.spmatrix, b: NDArray) -> tuple[NDArray, int]:
        M = LinearOperator(K.shape, self.lu.solve, dtype=float)
        iterations = [0]

        def count(_: float) -> None:
            iterations[0] += 1

        x, info = gmres(
            K, b, rtol=self.rtol, restart=self.max_iterations, maxiter=2, M=M,
            callback=count, callback_type="pr_norm",
        )  # fmt: skip
        if iterations[0] > self.max_iterations // 2:  # the factorization has gone stale
            self.lu = None
        return x, info

    def solve(self, K: sparse.spmatrix, b: NDArray) -> NDArray[np.float64]:
        """``K^-1 b`` for a square sparse ``K`` (n, n) and ``b`` (n,)."""
        if self.lu is not None and self.lu.shape == K.shape:
            x, info = self._gmres(K, b)
            if info == 0:
                return x
        K = K.tocsc()
        self.lu = splu(
            K, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True, "DiagPivotThresh": 0.0}
        )
        self.factorizations += 1
        x, info = self._gmres(K, b)
        if info == 0:
            return x
        self.lu = None
        return splu(K, permc_spec="MMD_AT_PLUS_A").solve(b)


def _newton(
    disc: Discretization,
    z: NDArray,
    free: NDArray[np.bool_],
    f_ext: NDArray,
    settings: ReferenceSettings,
    linear: LinearSolver,
) -> tuple[NDArray[np.float64], int]:
    """Newton iterations on the DOF vector ``z = [u, p]`` from a start whose fixed entries
    already hold their prescribed values; a backtracking line search keeps ``det F`` above
    ``settings.min_jacobian`` and lets the scaled residual norm decrease."""
    n_u = disc.n_u
    volume = float(disc.basis_u.dx.sum())
    n_free_u = int(free[:n_u].sum())

    def evaluate(y: NDArray) -> tuple[NDArray, float, bool]:
        with np.errstate(invalid="ignore"):  # J^(-2/3) of an inverted trial: rejected below
            state = material_state(disc, y[:n_u], y[n_u:], with_tangent=False)
            r = residual(disc, state, y[n_u:], f_ext)
        scale_u = max(np.linalg.norm(r[:n_u] + f_ext), np.linalg.norm(f_ext), 1e-300)
        r_free = r[free]
        err_u = np.linalg.norm(r_free[:n_free_u]) / scale_u
        err_p = np.linalg.norm(r_free[n_free_u:]) / volume
        return r_free, max(err_u, err_p), bool(state.J.min() > settings.min_jacobian)

    r, error, _ = evaluate(z)
    for iteration in range(settings.max_iterations):
        if error <= settings.tolerance:
            return z, iteration
        state = material_state(disc, z[:n_u], z[n_u:])
        dz = linear.solve(tangent_matrix(disc, state)[free][:, free], -r)
        if np.abs(dz[:n_free_u]).max() <= settings.step_tolerance:
            z = z.copy()
            z[free] += dz
            return z, iteration + 1
        step = 1.0
        while True:
            trial = z.copy()
            trial[free] += step * dz
            r_t, error_t, admissible = evaluate(trial)
            if admissible and error_t < (1.0 - 1e-4 * step) * error:
                break
            step *= 0.5
            if step < 1.0 / 64:
                raise ReferenceSolverError(
                    f"line search failed at Newton iteration {iteration} (error {error:.3g})"
                )
        z, r, error = trial, r_t, error_t
    if error <= settings.tolerance:
        return z, settings.max_iterations
    raise ReferenceSolverError(
        f"Newton did not converge in {settings.max_iterations} iterations (error {error:.3g})"
    )


def solve(
    disc: Discretization,
    fixed: NDArray,
    record: Sequence[float],
    body_force: ArrayLike = (0.0, 0.0, 0.0),
    prescribed: NDArray | None = None,
    settings: ReferenceSettings | None = None,
) -> ReferenceSolution:
    """Quasi-static equilibria under a proportional load ramp.

    At load factor ``s`` the body force is ``s * body_force`` and the fixed DOFs are held at
    ``s * prescribed``. Increments adapt (halved on failure, grown by 1.5 after easy steps,
    at most ``settings.max_increment``) and a linear predictor starts each Newton solve.

    Parameters
    ----------
    fixed : (n_fixed,) int
        Prescribed displacement DOFs (see `dofs_where`).
    record : sequence of float
        Increasing load factors at which the solution is recorded.
    body_force : (3,) float
        Body force at load factor 1, Pa/mm (force per reference volume).
    prescribed : (n_fixed,) float, optional
        Displacements of the fixed DOFs at load factor 1, mm; zero if omitted.

    Returns
    -------
    ReferenceSolution

    Raises
    ------
    ReferenceSolverError
        An increment failed after ``settings.max_cutbacks`` halvings.
    """
    settings = settings or ReferenceSettings()
    fixed = np.asarray(fixed, dtype=np.int64)
    values = np.zeros(len(fixed)) if prescribed is None else np.asarray(prescribed, float)
    f_unit = body_force_vector(disc, body_force)
    n_u = disc.n_u
    free = np.ones(n_u + disc.n_p, bool)
    free[fixed] = False
    z = np.zeros(n_u + disc.n_p)
    velocity = np.zeros_like(z)
    linear = LinearSolver()
    lam, increment, iterations = 0.0, min(float(record[0]), settings.max_increment), 0
    displacements, pressures = [], []
    for target in record:
        cutbacks = 0
        while lam < target - 1e-12:
            nxt = min(lam + increment, target)
            guess = z + (nxt - lam) * velocity
            guess[fixed] = nxt * values
            try:
                z_new, its = _newton(disc, guess, free, nxt * f_unit, settings, linear)
            except ReferenceSolverError as exc:
                cutbacks += 1
                increment *= 0.5
                if cutbacks > settings.max_cutbacks:
                    raise ReferenceSolverError(f"load factor {nxt:.4g}: {exc}") from exc
                continue
            velocity = (z_new - z) / (nxt - lam)
            z, lam, iterations = z_new, nxt, iterations + its
            if its <= 4:
                increment = min(1.5 * increment, settings.max_increment)
        displacements.append(z[:n_u].reshape(-1, 3).copy())
        pressures.append(z[n_u:].copy())
    return ReferenceSolution(
        disc,
        np.asarray(record, float),
        np.stack(displacements),
        np.stack(pressures) if disc.basis_p is not None else None,
        iterations,
        linear.factorizations,
    )


# --------------------------------------------------------------------------------------------
# Quantities of interest
# --------------------------------------------------------------------------------------------


def compliance(disc: Discretization, displacement: NDArray, force_density: ArrayLike) -> float:
    """Work of a constant body force on a displacement, ``int b . u dV``, Pa mm^3.

    Parameters
    ----------
    displacement : (N_nodes, 3)
        Nodal displacements, mm.
    force_density : (3,)
        Body force, Pa/mm.
    """
    return float(body_force_vector(disc, force_density) @ np.asarray(displacement).ravel())


def volume_change(disc: Discretization, displacement: NDArray) -> float:
    """``int (J - 1) dV``, mm^3, of the nodal displacements (N_nodes, 3), mm."""
    F = deformation_gradient(disc, np.asarray(displacement).ravel())
    return float(((np.linalg.det(F) - 1.0) * disc.basis_u.dx).sum())
