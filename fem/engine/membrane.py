"""Skin: an incompressible neo-Hookean membrane on the outer-surface triangles.

Each linear triangle of reference area ``A`` and thickness ``t`` stores

    W = A t mu/2 (I1 + 1/I3 - 3),    C = F_s^T F_s (2 x 2), I1 = tr C, I3 = det C,

the plane-stress neo-Hookean membrane whose thickness stretch is ``1/sqrt(I3)``
(incompressible). ``F_s`` (3 x 2) maps the triangle's reference in-plane frame to the current
configuration. Second Piola-Kirchhoff stress and material tangent:

    S = mu t (I - C^-1 / I3),
    CC = 2 mu t / I3 (C^-1 (.) C^-1 + C^-1 (x) C^-1),   (C^-1 (.) C^-1)_abcd = (Ci_ac Ci_bd + Ci_ad Ci_bc) / 2,

and with the 2-D shape gradients ``G`` (3 x 2) the nodal forces ``f_a = A F_s S G_a`` and the
stiffness ``K_ab = A [(G_a . S G_b) I + (F_s G_a) : CC : (F_s G_b)]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import sparse


def membrane_frame(points: NDArray, triangles: NDArray) -> tuple[NDArray, NDArray]:
    """Reference shape gradients in each triangle's own orthonormal in-plane frame.

    Returns
    -------
    grads : (S, 3, 2) float64
        ``dN_a / dxi_alpha``, 1/mm.
    areas : (S,) float64
        Reference areas, mm^2.
    """
    p = points[triangles]
    e1 = p[:, 1] - p[:, 0]
    n = np.cross(e1, p[:, 2] - p[:, 0])
    areas = 0.5 * np.linalg.norm(n, axis=1)
    if np.any(areas <= 0):
        raise ValueError(f"{int((areas <= 0).sum())} skin triangles have zero area")
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n / (2 * areas[:, None]), e1)
    local = np.stack(
        [np.einsum("sai,si->sa", p - p[:, :1], e) for e in (e1, e2)], axis=2
    )  # (S, 3, 2)
    D = np.swapaxes(local[:, 1:] - local[:, :1], 1, 2)  # (S, 2, 2)
    Dinv = np.linalg.inv(D)
    return np.concatenate([-Dinv.sum(axis=1, keepdims=True), Dinv], axis=1), areas


@dataclass
class SkinMembrane:
    """Neo-Hookean membrane on ``triangles`` (S, 3) of a mesh with reference ``points``.

    Parameters
    ----------
    mu : float
        Shear modulus, Pa.
    thickness : float
        Membrane thickness, mm.
    """

    points: NDArray
    triangles: NDArray
    mu: float
    thickness: float = 2.0
    grads: NDArray = field(init=False, repr=False)
    areas: NDArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, float)
        self.triangles = np.asarray(self.triangles, np.int64)
        self.grads, self.areas = membrane_frame(self.points, self.triangles)
        n_tri, n = len(self.triangles), len(self.points)
        self.dofs = (3 * self.triangles[:, :, None] + np.arange(3)).reshape(n_tri, 9)
        keys = (
            np.repeat(self.dofs, 9, axis=1).ravel() * (3 * n) + np.tile(self.dofs, (1, 9)).ravel()
        )
        unique, self._scatter = np.unique(keys, return_inverse=True)
        self._pattern = (unique // (3 * n), unique % (3 * n))
        self._ndof = 3 * n

    def _kinematics(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        Fs = np.swapaxes(x[self.triangles], 1, 2) @ self.grads  # (S, 3, 2)
        C = np.swapaxes(Fs, 1, 2) @ Fs  # (S, 2, 2), symmetric
        I3 = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] ** 2
        adjugate = np.stack([C[:, 1, 1], -C[:, 0, 1], -C[:, 0, 1], C[:, 0, 0]], axis=1)
        return Fs, C, adjugate.reshape(-1, 2, 2) / I3[:, None, None], I3

    def energy(self, x: NDArray) -> float:
        """Stored energy, Pa mm^3."""
        _, C, _, I3 = self._kinematics(x)
        w = 0.5 * self.mu * self.thickness * (np.trace(C, axis1=1, axis2=2) + 1.0 / I3 - 3.0)
        return float(self.areas @ w)

    def _stress(self, Ci: NDArray, I3: NDArray) -> NDArray:
        return self.mu * self.thickness * (np.eye(2) - Ci / I3[:, None, None])

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dW/dx`` flattened (3N,), Pa mm^2."""
        Fs, _, Ci, I3 = self._kinematics(x)
        fe = self.areas[:, None, None] * np.einsum(
            "sij,sjk,sak->sai", Fs, self._stress(Ci, I3), self.grads
        )
        return np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self._ndof)

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2W/dx2`` as CSR (3N, 3N), Pa mm."""
        Fs, _, Ci, I3 = self._kinematics(x)
        S = self._stress(Ci, I3)
        sym = 0.5 * (np.einsum("sac,sbd->sabcd", Ci, Ci) + np.einsum("sad,sbc->sabcd", Ci, Ci))
        CC = (2.0 * self.mu * self.thickness / I3)[:, None, None, None, None] * (
            sym + np.einsum("sab,scd->sabcd", Ci, Ci)
        )
        geometric = np.einsum("saj,sjk,sbk->sab", self.grads, S, self.grads)  # (S, 3, 3)
        # Material part: d(E_ab)/dx_{n,i} = sym(F_ia G_nb); with CC's minor symmetry use F_ia G_nb.
        FG = np.einsum("sia,snb->sniab", Fs, self.grads)  # (S, 3 nodes, 3 dims, 2, 2)
        Km = np.einsum("sniab,sabcd,smkcd->snimk", FG, CC, FG)
        Ke = Km + geometric[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        Ke *= self.areas[:, None, None, None, None]
        data = np.bincount(self._scatter, weights=Ke.ravel(), minlength=len(self._pattern[0]))
        return sparse.csr_matrix((data, self._pattern), shape=(self._ndof, self._ndof))
