"""Energy, internal forces and tangent stiffness of neo-Hookean linear tetrahedra.

Total-Lagrangian, one integration point per element (P1 gradients are constant). The strain
energy of the body is

    W(x) = sum_e V_e psi_iso(F_e) + sum_p V_p U(Jbar_p),    Jbar_p = sum_e s_pe J_e / V_p,

with volumetric *patches* p: either the elements themselves (``averaging="element"``, plain
P1, which locks at nu = 0.495) or the nodes (``averaging="nodal"``: each element gives a
quarter of its volume to each of its nodes, ``s_ne = V_e / 4``), the average-nodal-pressure
tetrahedron of Bonet & Burton (1998). Because nodal averaging is done on the energy, forces
and tangent follow by differentiation and the tangent is symmetric:

    f   = sum_e V_e P_iso(F_e) : dF_e/dx  +  sum_e q_e dJ_e/dx,          q_e = sum_p s_pe U'(Jbar_p)
    K   = sum_e dF:[V_e A_iso + q_e d2J/dF2]:dF  +  B^T diag(V_p U''(Jbar_p)) B,
    B   = diag(1/V_p) S dJ/dx      (row p: the gradient of Jbar_p).

The element blocks (with the element patches' share of the last term) are scattered into a
fixed sparsity pattern with ``np.bincount`` (the "hand-vectorised kernel"); the nodal patches'
term stays the factor ``sqrt(c) B`` of a `SplitTangent`, whose 2-ring coupling a direct solver
never forms; `fem.engine.assembly.skfem_tangent` is the scikit-fem reference it is
tested against.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import skfem
from numpy.typing import NDArray
from scipy import sparse

from fem.contract.quality import signed_volume
from fem.engine.material import (
    isochoric_energy,
    isochoric_pk1,
    isochoric_tangent,
    volumetric_energy,
    volumetric_pressure,
    volumetric_stiffness,
)
from fem.engine.tensor import cofactor, determinant, inverse


def shape_gradients(
    points: NDArray, cells: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Reference gradients of the P1 shape functions and element volumes.

    Returns
    -------
    grads : (E, 4, 3) float64
        ``dN_a / dX_j`` of each element's four nodes, 1/mm.
    volumes : (E,) float64
        Reference volumes, mm^3 (must be positive).
    """
    p = points[cells]
    D = np.swapaxes(p[:, 1:] - p[:, :1], 1, 2)  # (E, 3, 3): columns X_b - X_0
    Dinv = np.linalg.inv(D)  # rows: gradients of N_1..N_3
    grads = np.concatenate([-Dinv.sum(axis=1, keepdims=True), Dinv], axis=1)
    return grads, signed_volume(points, cells)


def gradient_operator(cells: NDArray, grads: NDArray, n_nodes: int) -> sparse.csr_matrix:
    """``D`` with ``F = (D @ x.ravel()).reshape(E, 3, 3)``: ``F_e,ij = sum_a x_{a,i} G_e,aj``.

    Its transpose scatters element stresses to nodal forces, ``f = D^T vec(P)``
    (``f_{a,i} = sum_j P_ij G_aj``). Shape (9E, 3N), four entries per row.
    """
    n_el = len(cells)
    shape = (n_el, 3, 4, 3)  # [e, i, a, j]
    rows = 9 * np.arange(n_el)[:, None, None, None] + 3 * np.arange(3)[None, :, None, None]
    rows = rows + np.arange(3)[None, None, None, :]
    cols = 3 * cells[:, None, :, None] + np.arange(3)[None, :, None, None]
    values = np.broadcast_to(grads[:, None, :, :], shape)
    return sparse.csr_matrix(
        (
            values.ravel(),
            (np.broadcast_to(rows, shape).ravel(), np.broadcast_to(cols, shape).ravel()),
        ),
        shape=(9 * n_el, 3 * n_nodes),
    )


def element_blocks(
    F: NDArray, grads: NDArray, volumes: NDArray, mu: NDArray, q: NDArray
) -> NDArray[np.float64]:
    """Element tangents ``K_e[a, i, b, k] = G_aj C_ijkl G_bl`` of ``C = V A_iso + q d2J/dF2``,
    shape (E, 4, 3, 4, 3), Pa mm.

    With ``h_a = F^-1^T G_a``, ``f_a = F G_a``, ``a = J^-2/3`` and ``w = V mu a`` the contraction
    is written out (`fem.engine.material.isochoric_tangent`, ``d2J/dF2 = J (F^-T (x) F^-T -
    F^-1_li F^-1_jk)``) instead of forming the fourth-order tensor (4x faster):

        K_e = w (G_a . G_b) d_ik - 2/3 w (h_ai f_bk + f_ai h_bk)
              + (2/9 w I1 + q J) h_ai h_bk + (w I1 / 3 - q J) h_bi h_ak.
    """
    Finv, J = inverse(F)
    h = grads @ Finv  # (E, 4, 3): h_ai = F^-1_ji G_aj
    f = grads @ np.swapaxes(F, 1, 2)  # (E, 4, 3): f_ai = F_il G_al
    w = volumes * mu * J ** (-2.0 / 3.0)
    I1 = np.einsum("eij,eij->e", F, F)
    c1 = (-2.0 / 3.0 * w)[:, None]
    c2 = (2.0 / 9.0 * w * I1 + q * J)[:, None]
    c3 = (w * I1 / 3.0 - q * J)[:, None]
    H, Fv = h.reshape(-1, 12), f.reshape(-1, 12)
    K = H[:, :, None] * (c2 * H + c1 * Fv)[:, None, :]  # c2 h h + c1 h f
    K += (c1 * Fv)[:, :, None] * H[:, None, :]  # c1 f_ai h_bk
    K = K.reshape(-1, 4, 3, 4, 3)
    swapped = (c3.reshape(-1, 1) * H)[:, :, None] * H[:, None, :]  # [a, k, b, i]: h_ak h_bi
    K += swapped.reshape(-1, 4, 3, 4, 3).transpose(0, 1, 4, 3, 2)
    gg = w[:, None, None] * (grads @ np.swapaxes(grads, 1, 2))  # (E, 4, 4): w G_a . G_b
    for i in range(3):  # ... times d_ik
        K[:, :, i, :, i] += gg
    return K


def same_pattern(pattern: tuple[NDArray, NDArray] | None, K: sparse.csr_matrix) -> bool:
    """Whether the CSR matrix ``K`` has the pattern ``(indptr, indices)`` (None: no pattern)."""
    return (
        pattern is not None
        and np.array_equal(pattern[0], K.indptr)
        and np.array_equal(pattern[1], K.indices)
    )


class BlockPattern:
    """A fixed CSR pattern (n, n) holding dense blocks over sets of DOFs, and where each set's
    entries go: parts scatter their element blocks with one ``np.bincount`` (the
    "hand-vectorised kernel") instead of adding sparse matrices.

    Parameters
    ----------
    n : int
        Number of DOFs.
    dof_sets : sequence of (M, k) int
        Each set's DOFs per block (element, triangle, node).
    """

    def __init__(self, n: int, dof_sets: Sequence[NDArray]):
        keys = [self._keys(d, n) for d in dof_sets]
        unique = np.unique(np.concatenate(keys))
        self.n = n
        self.scatters = [np.searchsorted(unique, k) for k in keys]
        self.indices = (unique % n).astype(np.int32)
        self.indptr = np.searchsorted(unique // n, np.arange(n + 1)).astype(np.int32)

    @staticmethod
    def _keys(dofs: NDArray, n: int) -> NDArray[np.int64]:
        k = dofs.shape[1]
        return (np.repeat(dofs, k, axis=1) * np.int64(n) + np.tile(dofs, (1, k))).ravel()

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def scatter(self, data: NDArray, which: int, blocks: NDArray) -> None:
        """Add the blocks (M, k, k) of DOF set ``which`` to ``data`` (nnz,)."""
        data += np.bincount(self.scatters[which], weights=blocks.ravel(), minlength=self.nnz)

    def matrix(self, data: NDArray) -> sparse.csr_matrix:
        """The CSR matrix with these values (sorted indices, full blocks)."""
        K = sparse.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        K.has_sorted_indices = True
        return K


@dataclass(frozen=True)
class SplitTangent:
    """A symmetric tangent kept as ``K = local + factor^T factor``.

    Nodal averaging couples every node with its patch's patch (a 2-ring stencil): the
    condensed ``K`` has 2.5x the nonzeros of ``local`` and its LU fills in far more. Direct
    solvers factorize the equivalent augmented matrix ``[[local, factor^T], [factor, -I]]``
    instead (`augmented`; eliminating its last ``P`` unknowns, ``q = factor u``, gives
    ``K u = b`` exactly), whose stencil is the 1-ring: on a breast refined to 139,200
    tetrahedra (79,287 DOFs) MKL PARDISO factorized it in 28 s against 83 s for ``K``.

    Parameters
    ----------
    local : (n, n) CSR
        The element blocks (with the element-wise share of the volumetric energy) and the
        parts' blocks, Pa mm.
    factor : (P, n) CSR
        ``sqrt(c) dJbar/dx`` of the ``P`` nodal patches (`HyperelasticBody.volumetric_factor`),
        sqrt(Pa mm).
    """

    local: sparse.csr_matrix
    factor: sparse.csr_matrix

    @property
    def shape(self) -> tuple[int, int]:
        return self.local.shape

    @property
    def dtype(self) -> np.dtype:
        return self.local.dtype

    def __matmul__(self, v: NDArray) -> NDArray[np.float64]:
        return self.local @ v + self.factor.T @ (self.factor @ v)

    def diagonal(self) -> NDArray[np.float64]:
        return (
            self.local.diagonal()
            + np.asarray(self.factor.multiply(self.factor).sum(axis=0)).ravel()
        )

    def full(self) -> sparse.csr_matrix:
        """The condensed ``local + factor^T factor`` (n, n)."""
        return (self.local + self.factor.T @ self.factor).tocsr()

    def toarray(self) -> NDArray[np.float64]:
        return self.full().toarray()

    def submatrix(self, keep: NDArray[np.bool_]) -> SplitTangent:
        """The rows and columns of the DOFs ``keep``."""
        return SplitTangent(self.local[keep][:, keep], self.factor[:, keep].tocsr())

    def augmented(self) -> sparse.csr_matrix:
        """``[[local, factor^T], [factor, -I]]`` (n + P, n + P), symmetric indefinite."""
        eye = sparse.identity(self.factor.shape[0], format="csr")
        return sparse.bmat([[self.local, self.factor.T], [self.factor, -eye]], format="csr")


def assemble(n: int, dofs: NDArray, blocks: NDArray) -> sparse.csr_matrix:
    """CSR matrix (n, n) of element ``blocks`` (M, k, k) over ``dofs`` (M, k)."""
    pattern = BlockPattern(n, [dofs])
    data = np.zeros(pattern.nnz)
    pattern.scatter(data, 0, blocks)
    return pattern.matrix(data)


@dataclass
class HyperelasticBody:
    """A tetrahedral neo-Hookean body with a fixed sparsity pattern for its tangent.

    Parameters
    ----------
    points : (N, 3) float
        Reference node coordinates, mm.
    cells : (E, 4) int
        Positively oriented tetrahedra.
    mu, kappa : (E,) float
        Shear and bulk moduli per element, Pa.
    averaging : {"nodal", "element"}
        Volumetric patches: nodal averaging (locking-free) or plain P1.
    stabilization : float
        With nodal averaging, the share ``alpha`` of the volumetric energy kept on the elements:
        ``(1 - alpha) sum_n V_n U(Jbar_n) + alpha sum_e V_e U(J_e)``. Pure nodal averaging
        leaves element-level volume changes that average out over a node's patch almost free
        (a spurious mode that made compression fail with elements at J = 0.25); a small alpha
        suppresses it at the price of a little of plain P1's locking.

    Units: with mm and Pa, energies are in Pa mm^3 = 1e-9 J and forces in Pa mm^2 = 1e-6 N.
    """

    points: NDArray
    cells: NDArray
    mu: NDArray
    kappa: NDArray
    averaging: str = "nodal"
    stabilization: float = 0.0
    grads: NDArray = field(init=False, repr=False)
    volumes: NDArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.averaging not in ("nodal", "element"):
            raise ValueError(f"averaging must be 'nodal' or 'element', got {self.averaging!r}")
        self.points = np.asarray(self.points, float)
        self.cells = np.asarray(self.cells, np.int64)
        n_el = len(self.cells)
        self.mu = np.broadcast_to(np.asarray(self.mu, float), (n_el,)).copy()
        self.kappa = np.broadcast_to(np.asarray(self.kappa, float), (n_el,)).copy()
        self.grads, self.volumes = shape_gradients(self.points, self.cells)
        if np.any(self.volumes <= 0):
            raise ValueError(
                f"{int((self.volumes <= 0).sum())} elements have non-positive reference volume"
            )
        n = len(self.points)
        if not 0.0 <= self.stabilization <= 1.0:
            raise ValueError(f"stabilization must lie in [0, 1], got {self.stabilization}")
        element_patches = sparse.diags(self.volumes).tocsr()
        if self.averaging == "nodal":
            rows = self.cells.ravel()
            cols = np.repeat(np.arange(n_el), 4)
            S = sparse.csr_matrix((np.repeat(self.volumes / 4.0, 4), (rows, cols)), shape=(n, n_el))
            # Patch bulk modulus: volume average of the element moduli of the patch.
            self.patch_kappa = (S @ self.kappa) / np.asarray(S.sum(axis=1)).ravel()
            if self.stabilization > 0:  # weighted patches: the weights scale the patch volumes
                S = sparse.vstack(
                    [(1 - self.stabilization) * S, self.stabilization * element_patches]
                ).tocsr()
                self.patch_kappa = np.concatenate([self.patch_kappa, self.kappa])
        else:
            S = element_patches
            self.patch_kappa = self.kappa
        self.S = S
        self.patch_volume = np.asarray(S.sum(axis=1)).ravel()
        # DOF map and the fixed CSR pattern of the element blocks.
        self.dofs = (3 * self.cells[:, :, None] + np.arange(3)).reshape(n_el, 12)
        self._ndof = 3 * n
        self._D = gradient_operator(self.cells, self.grads, n)
        self._DT = self._D.T.tocsr()
        # B = diag(1/V_p) S dJ/dx, the gradients of the patch averages Jbar_p, has a fixed
        # structure and data linear in dJ/dx (E, 4, 3): B.data = bincount(_b_entry,
        # _b_weight * dJ[_b_source]), one term per (patch, element of the patch, DOF).
        # Only the nodal patches couple elements (the first n rows of S); the element patches'
        # share of the volumetric energy is element-local (`tangent_blocks`).
        self._coupled = n if self.averaging == "nodal" else 0
        Sc = (sparse.diags(1.0 / self.patch_volume) @ S)[: self._coupled].tocoo()
        patch = np.repeat(Sc.row.astype(np.int64), 12)  # keys pass 2^31 on real-size meshes
        dof = self.dofs[Sc.col].ravel()
        keys = patch * (3 * n) + dof
        unique, self._b_entry = np.unique(keys, return_inverse=True)
        self._b_source = (12 * Sc.col[:, None] + np.arange(12)).ravel()
        self._b_weight = np.repeat(Sc.data, 12)
        self._b_pattern = (unique // (3 * n), unique % (3 * n))
        self._cache: tuple[NDArray, tuple[NDArray, NDArray, NDArray]] | None = None

    @property
    def n_dofs(self) -> int:
        return self._ndof

    def _volumetric(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """``F`` (E, 3, 3), ``J`` (E,) and the patch averages ``Jbar`` (P,) at ``x``; the
        last ones are kept (the line search's trial is the next iteration's state)."""
        x = np.asarray(x, float)
        if self._cache is not None and np.array_equal(self._cache[0], x):
            return self._cache[1]
        F = (self._D @ x.reshape(-1)).reshape(-1, 3, 3)
        J = determinant(F)
        state = F, J, (self.S @ J) / self.patch_volume
        self._cache = x.copy(), state
        return state

    def min_jacobian(self, x: NDArray) -> float:
        """Smallest ``det F`` over the elements (<= 0: an element is inverted)."""
        return float(self._volumetric(x)[1].min())

    def energy(self, x: NDArray) -> float:
        """Strain energy at node positions ``x`` (N, 3), Pa mm^3."""
        F, _, Jbar = self._volumetric(x)
        return float(
            self.volumes @ isochoric_energy(F, self.mu)
            + self.patch_volume @ volumetric_energy(Jbar, self.patch_kappa)
        )

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dW/dx = D^T vec(V P_iso + q cof F)``, flattened (3N,), Pa mm^2 (``dJ/dF = cof F``)."""
        F, _, Jbar = self._volumetric(x)
        q = self.S.T @ volumetric_pressure(Jbar, self.patch_kappa)  # (E,)
        stress = self.volumes[:, None, None] * isochoric_pk1(F, self.mu)
        stress += q[:, None, None] * cofactor(F)
        return self._DT @ stress.reshape(-1)

    def tangent_blocks(self, x: NDArray) -> NDArray[np.float64]:
        """Element blocks (E, 12, 12) of the tangent over `dofs`, with the element patches'
        volumetric stiffness and without the coupling of the nodal patches
        (`volumetric_factor`), Pa mm."""
        F, _, Jbar = self._volumetric(x)
        q = self.S.T @ volumetric_pressure(Jbar, self.patch_kappa)
        blocks = element_blocks(F, self.grads, self.volumes, self.mu, q).reshape(-1, 12, 12)
        m = self._coupled
        if len(Jbar) > m:  # element patches: c_e dJ_e/dx (dJ_e/dx)^T
            c = self.patch_volume[m:] * volumetric_stiffness(Jbar[m:], self.patch_kappa[m:])
            dJ = (self.grads @ np.swapaxes(cofactor(F), 1, 2)).reshape(-1, 12)
            blocks += c[:, None, None] * dJ[:, :, None] * dJ[:, None, :]
        return blocks

    def volumetric_factor(self, x: NDArray) -> sparse.csr_matrix:
        """``sqrt(c) B`` with ``c = V_p U''(Jbar_p) >= 0`` and ``B = dJbar/dx`` (P, 3N) of the
        ``P`` nodal patches (none for plain P1): the rest of the tangent is
        ``B^T diag(c) B``, the square of this."""
        F, _, Jbar = self._volumetric(x)
        m = self._coupled
        dJ = (self.grads @ np.swapaxes(cofactor(F), 1, 2)).reshape(-1)  # dJ_e/dx_{a,i}
        c = self.patch_volume[:m] * volumetric_stiffness(Jbar[:m], self.patch_kappa[:m])
        values = np.bincount(
            self._b_entry,
            weights=self._b_weight * dJ[self._b_source],
            minlength=len(self._b_pattern[0]),
        )
        return sparse.csr_matrix(
            (values * np.sqrt(c)[self._b_pattern[0]], self._b_pattern), shape=(m, self._ndof)
        )

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2W/dx2`` as a symmetric CSR matrix (3N, 3N), Pa mm."""
        B = self.volumetric_factor(x)
        return (assemble(self._ndof, self.dofs, self.tangent_blocks(x)) + B.T @ B).tocsr()


@dataclass
class Model:
    """A solid body plus parts (skin membrane, plates' friction): energies, forces and
    tangents add. The plates' non-penetration bounds and lagged normal forces are handled in
    node frames (`fem.engine.constraints.FramedModel`).

    Each part gives its tangent as blocks over fixed DOFs (``dofs`` (M, k) and
    ``tangent_blocks(x)`` (M, k, k)); the tangent is scattered into one fixed `BlockPattern`
    (the body's elements and the parts' blocks), built on the first call; nodal averaging's
    ``B^T B`` stays a factor (`SplitTangent`).
    """

    body: HyperelasticBody
    parts: tuple = ()
    _pattern: BlockPattern | None = field(default=None, init=False, repr=False)

    @property
    def cells(self) -> NDArray:
        return self.body.cells

    def min_jacobian(self, x: NDArray) -> float:
        return self.body.min_jacobian(x)

    def energy(self, x: NDArray) -> float:
        return self.body.energy(x) + sum(p.energy(x) for p in self.parts)

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        return self.body.internal_force(x) + sum(
            (p.internal_force(x) for p in self.parts), start=0.0
        )

    def tangent(self, x: NDArray) -> SplitTangent:
        if self._pattern is None:
            self._pattern = BlockPattern(
                self.body.n_dofs, [self.body.dofs, *(p.dofs for p in self.parts)]
            )
        data = np.zeros(self._pattern.nnz)
        self._pattern.scatter(data, 0, self.body.tangent_blocks(x))
        for i, p in enumerate(self.parts, start=1):
            self._pattern.scatter(data, i, p.tangent_blocks(x))
        return SplitTangent(self._pattern.matrix(data), self.body.volumetric_factor(x))


def skfem_tangent(body: HyperelasticBody, x: NDArray) -> sparse.csr_matrix:
    """Reference tangent of the plain-P1 body (``averaging="element"``) assembled by scikit-fem.

    The integrand is ``dv : A(F) : du`` with the full decoupled material tangent, one
    integration point per element; used to test `HyperelasticBody.tangent`.
    """
    if body.averaging != "element":
        raise ValueError("the scikit-fem reference assembles the plain P1 (element) formulation")
    mesh = skfem.MeshTet(body.points.T, body.cells.T, sort_t=False)
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()), intorder=1)
    u = (x - body.points).ravel()  # our DOF order: 3 * node + component
    n_qp = basis.X.shape[-1]
    mu_e = np.repeat(body.mu[:, None], n_qp, axis=1)
    kappa_e = np.repeat(body.kappa[:, None], n_qp, axis=1)

    @skfem.BilinearForm
    def form(du, dv, w):
        F = np.eye(3)[:, :, None, None] + w["disp"].grad  # (3, 3, E, Q)
        Fq = np.moveaxis(F, (0, 1), (-2, -1))  # (E, Q, 3, 3)
        J = np.linalg.det(Fq)
        Finv = np.linalg.inv(Fq)
        FinvT = np.swapaxes(Finv, -1, -2)
        A = isochoric_tangent(Fq, w["mu"])
        k = w["kappa"][..., None, None, None, None]
        A = A + k * (J * (2 * J - 1))[..., None, None, None, None] * np.einsum(
            "...ij,...kl->...ijkl", FinvT, FinvT
        )
        A = A - (
            k * (J - 1)[..., None, None, None, None] * J[..., None, None, None, None]
        ) * np.einsum("...jk,...li->...ijkl", Finv, Finv)
        A = np.moveaxis(A, (-4, -3, -2, -1), (0, 1, 2, 3))  # (3, 3, 3, 3, E, Q)
        return np.einsum("ijkl...,kl...,ij...->...", A, du.grad, dv.grad)

    dofmap = basis.nodal_dofs.T.ravel()  # skfem DOF of our DOF 3 * node + component
    u_sk = np.zeros(basis.N)
    u_sk[dofmap] = u
    K = form.assemble(basis, disp=basis.interpolate(u_sk), mu=mu_e, kappa=kappa_e)
    return K[dofmap][:, dofmap].tocsr()
