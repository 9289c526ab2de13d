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

The element blocks are scattered into a fixed sparsity pattern with ``np.bincount`` (the
"hand-vectorised kernel"); `fem.engine.assembly.skfem_tangent` is the scikit-fem reference it is
tested against.
"""

from __future__ import annotations

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


def deformation_gradient(x: NDArray, cells: NDArray, grads: NDArray) -> NDArray[np.float64]:
    """``F_e = sum_a x_a (x) grad N_a``, shape (E, 3, 3), for current node positions ``x``."""
    return np.swapaxes(x[cells], 1, 2) @ grads


def jacobian_gradient(F: NDArray, grads: NDArray) -> NDArray[np.float64]:
    """``dJ_e / dx_{a,i} = J F^-T_ij G_aj = (cof F)_ij G_aj``, shape (E, 4, 3)."""
    return grads @ np.swapaxes(cofactor(F), 1, 2)


def jacobian_second_derivative(F: NDArray) -> NDArray[np.float64]:
    """``d2 J / dF_ij dF_kl = J (F^-T_ij F^-T_kl - F^-1_jk F^-1_li)``, shape (E, 3, 3, 3, 3)."""
    Finv, J = inverse(F)
    J = J[:, None, None, None, None]
    FinvT = np.swapaxes(Finv, 1, 2)
    return J * (np.einsum("eij,ekl->eijkl", FinvT, FinvT) - np.einsum("ejk,eli->eijkl", Finv, Finv))


def element_stiffness(C: NDArray, grads: NDArray) -> NDArray[np.float64]:
    """``K_e[a, i, b, k] = G_aj C_ijkl G_bl``: a fourth-order tensor per element pulled back to
    nodal blocks, shape (E, 4, 3, 4, 3); two batched matrix products instead of an einsum."""
    n = len(C)
    X = (C.reshape(n, 27, 3) @ np.swapaxes(grads, 1, 2)).reshape(n, 3, 3, 3, 4)  # [i, j, k, b]
    X = np.swapaxes(X, 1, 2).reshape(n, 3, 36)  # [j, (i, k, b)]
    K = (grads @ X).reshape(n, 4, 3, 3, 4)  # [a, i, k, b]
    return np.swapaxes(K, 3, 4)


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
        rows = np.repeat(self.dofs, 12, axis=1).ravel()
        cols = np.tile(self.dofs, (1, 12)).ravel()
        keys = rows * (3 * n) + cols
        unique, self._scatter = np.unique(keys, return_inverse=True)
        self._pattern = (unique // (3 * n), unique % (3 * n))
        self._ndof = 3 * n
        # dJ/dx as an (E, 3N) CSR with a fixed structure: only its data changes.
        self._grad_rows = np.repeat(np.arange(n_el), 12)
        self._grad_cols = self.dofs.ravel()

    @property
    def n_dofs(self) -> int:
        return self._ndof

    def _volumetric(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        F = deformation_gradient(x, self.cells, self.grads)
        J = determinant(F)
        Jbar = (self.S @ J) / self.patch_volume
        return F, J, Jbar

    def min_jacobian(self, x: NDArray) -> float:
        """Smallest ``det F`` over the elements (<= 0: an element is inverted)."""
        return float(determinant(deformation_gradient(x, self.cells, self.grads)).min())

    def energy(self, x: NDArray) -> float:
        """Strain energy at node positions ``x`` (N, 3), Pa mm^3."""
        F, _, Jbar = self._volumetric(x)
        return float(
            self.volumes @ isochoric_energy(F, self.mu)
            + self.patch_volume @ volumetric_energy(Jbar, self.patch_kappa)
        )

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dW/dx``, flattened (3N,), Pa mm^2."""
        F, _, Jbar = self._volumetric(x)
        q = self.S.T @ volumetric_pressure(Jbar, self.patch_kappa)  # (E,)
        P = isochoric_pk1(F, self.mu)
        fe = self.volumes[:, None, None] * np.einsum("eij,eaj->eai", P, self.grads)
        fe += q[:, None, None] * jacobian_gradient(F, self.grads)
        return np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self._ndof)

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2W/dx2`` as a symmetric CSR matrix (3N, 3N), Pa mm."""
        F, _, Jbar = self._volumetric(x)
        q = self.S.T @ volumetric_pressure(Jbar, self.patch_kappa)
        C = self.volumes[:, None, None, None, None] * isochoric_tangent(F, self.mu)
        C += q[:, None, None, None, None] * jacobian_second_derivative(F)
        Ke = element_stiffness(C, self.grads)
        data = np.bincount(self._scatter, weights=Ke.ravel(), minlength=len(self._pattern[0]))
        K = sparse.csr_matrix((data, self._pattern), shape=(self._ndof, self._ndof))
        dJ = jacobian_gradient(F, self.grads).reshape(-1)
        G = sparse.csr_matrix(
            (dJ, (self._grad_rows, self._grad_cols)), shape=(len(self.cells), self._ndof)
        )
        B = sparse.diags(1.0 / self.patch_volume) @ self.S @ G
        c = self.patch_volume * volumetric_stiffness(Jbar, self.patch_kappa)
        return (K + B.T @ sparse.diags(c) @ B).tocsr()


@dataclass
class Model:
    """A solid body plus parts (skin membrane, plates' friction): energies, forces and
    tangents add. The plates' non-penetration bounds and lagged normal forces are handled in
    node frames (`fem.engine.constraints.FramedModel`)."""

    body: HyperelasticBody
    parts: tuple = ()

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

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        K = self.body.tangent(x)
        for p in self.parts:
            K = K + p.tangent(x)
        return K.tocsr()


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
