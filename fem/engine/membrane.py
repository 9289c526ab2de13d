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

A membrane has no bending stiffness: under in-plane compression it wrinkles, and a compressed
neo-Hookean membrane (``S < 0``) makes the equilibrium non-unique (a node of the skin pops in or
out by millimetres depending on the load increments). With ``tension_field`` (default) the
energy is relaxed as in tension-field theory (Pipkin 1986): with the principal values
``c1 >= c2`` of ``C`` and the natural width of uniaxial tension ``c2 = c1^-1/2`` (where
``S_2 = 0``), a triangle is

* taut (``c2 >= c1^-1/2``): ``W`` as above;
* wrinkled (``c1 > 1 > ...``, ``c2 < c1^-1/2``): ``W = A t mu/2 (c1 + 2 c1^-1/2 - 3)``, the
  uniaxial tension along the first principal direction ``n1``,
  ``S = mu t (1 - c1^-3/2) n1 n1``, ``CC = 4 [W'' P (x) P + W' / (c1 - c2) M (x) M]`` with
  ``P = n1 n1``, ``M = (n1 n2 + n2 n1) / sqrt 2``;
* slack (``c1 <= 1``): no energy, no stress.

The relaxed energy is continuous with continuous stress; it never carries compression, so the
skin adds no negative geometric stiffness.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from fem.engine.assembly import assemble


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
    tension_field : bool
        Relax the energy so that the membrane wrinkles instead of carrying compression.
    """

    points: NDArray
    triangles: NDArray
    mu: float
    thickness: float = 2.0
    tension_field: bool = True
    grads: NDArray = field(init=False, repr=False)
    areas: NDArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, float)
        self.triangles = np.asarray(self.triangles, np.int64)
        self.grads, self.areas = membrane_frame(self.points, self.triangles)
        self.dofs = (3 * self.triangles[:, :, None] + np.arange(3)).reshape(-1, 9)
        self._ndof = 3 * len(self.points)
        self._cache: tuple[NDArray, tuple[NDArray, NDArray, NDArray]] | None = None

    def _kinematics(self, x: NDArray) -> tuple[NDArray, NDArray]:
        Fs = np.swapaxes(x[self.triangles], 1, 2) @ self.grads  # (S, 3, 2)
        return Fs, np.swapaxes(Fs, 1, 2) @ Fs  # C (S, 2, 2), symmetric

    def response(self, C: NDArray, tangent: bool = True) -> tuple[NDArray, NDArray, NDArray | None]:
        """Energy per reference area (S,), Pa mm; stress ``S`` (S, 2, 2), Pa mm; and material
        tangent ``CC = 2 dS/dC`` (S, 2, 2, 2, 2), Pa mm (None unless ``tangent``), of the right
        Cauchy-Green tensors ``C`` (S, 2, 2) (module docstring)."""
        mt = self.mu * self.thickness
        a, b, d = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
        I3 = a * d - b**2
        Ci = np.stack([d, -b, -b, a], axis=1).reshape(-1, 2, 2) / I3[:, None, None]
        w = 0.5 * mt * (a + d + 1.0 / I3 - 3.0)
        S = mt * (np.eye(2) - Ci / I3[:, None, None])
        CC = None
        if tangent:
            sym = 0.5 * (np.einsum("sac,sbd->sabcd", Ci, Ci) + np.einsum("sad,sbc->sabcd", Ci, Ci))
            CC = (2.0 * mt / I3)[:, None, None, None, None] * (
                sym + np.einsum("sab,scd->sabcd", Ci, Ci)
            )
        if not self.tension_field:
            return w, S, CC
        # principal values c1 >= c2 and directions n1 (angle theta), n2 of the 2 x 2 C
        radius = np.hypot(0.5 * (a - d), b)
        c1, c2 = 0.5 * (a + d) + radius, 0.5 * (a + d) - radius
        slack = c1 <= 1.0
        k = ~slack & (c2 < c1**-0.5)  # wrinkled
        theta = 0.5 * np.arctan2(2.0 * b[k], (a - d)[k])
        n1 = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        n2 = np.stack([-n1[:, 1], n1[:, 0]], axis=1)
        P = n1[:, :, None] * n1[:, None, :]
        d1 = 0.5 * mt * (1.0 - c1[k] ** -1.5)  # W'(c1)
        w[k] = 0.5 * mt * (c1[k] + 2.0 * c1[k] ** -0.5 - 3.0)
        S[k] = 2.0 * d1[:, None, None] * P
        w[slack], S[slack] = 0.0, 0.0
        if tangent:
            M = (n1[:, :, None] * n2[:, None, :] + n2[:, :, None] * n1[:, None, :]) / np.sqrt(2)
            d2 = 0.75 * mt * c1[k] ** -2.5  # W''(c1)
            CC[k] = 4.0 * (
                d2[:, None, None, None, None] * P[:, :, :, None, None] * P[:, None, None]
                + (d1 / (c1[k] - c2[k]))[:, None, None, None, None]
                * M[:, :, :, None, None]
                * M[:, None, None]
            )
            CC[slack] = 0.0
        return w, S, CC

    def _stress(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """``F_s`` (S, 3, 2), energy density (S,) and stress (S, 2, 2) at ``x``; the last ones
        are kept (the line search's energy and the next iteration's force share a state)."""
        if self._cache is not None and np.array_equal(self._cache[0], x):
            return self._cache[1]
        Fs, C = self._kinematics(x)
        w, S, _ = self.response(C, tangent=False)
        self._cache = np.array(x, float), (Fs, w, S)
        return Fs, w, S

    def energy(self, x: NDArray) -> float:
        """Stored energy, Pa mm^3."""
        return float(self.areas @ self._stress(x)[1])

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dW/dx`` flattened (3N,), Pa mm^2."""
        Fs, _, S = self._stress(x)
        fe = self.areas[:, None, None] * (self.grads @ np.swapaxes(Fs @ S, 1, 2))  # A F_s S G_a
        return np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self._ndof)

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2W/dx2`` as CSR (3N, 3N), Pa mm."""
        return assemble(self._ndof, self.dofs, self.tangent_blocks(x))

    def tangent_blocks(self, x: NDArray) -> NDArray[np.float64]:
        """Triangle blocks (S, 9, 9) of the tangent over `dofs`, Pa mm."""
        Fs, C = self._kinematics(x)
        _, S, CC = self.response(C)
        geometric = self.grads @ S @ np.swapaxes(self.grads, 1, 2)  # (S, 3, 3): G_a . S G_b
        # Material part: d(E_ab)/dx_{n,i} = sym(F_ia G_nb); with CC's minor symmetry use F_ia G_nb.
        FG = (self.grads[:, :, None, None, :] * Fs[:, None, :, :, None]).reshape(-1, 9, 4)
        Ke = (FG @ CC.reshape(-1, 4, 4) @ np.swapaxes(FG, 1, 2)).reshape(-1, 3, 3, 3, 3)
        for i in range(3):
            Ke[:, :, i, :, i] += geometric
        Ke *= self.areas[:, None, None, None, None]
        return Ke.reshape(-1, 9, 9)
