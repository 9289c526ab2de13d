"""Contact of surface nodes with rigid compression plates: exact non-penetration, Coulomb friction.

A plate is the plane ``z = height`` (cranio-caudal axis z) covering the region anterior to its
chest-side edge, ``y >= chest_edge``. The body lies above a lower plate (``side = +1``) and
below an upper plate (``side = -1``).

Normal contact is a *bound* on the z coordinate of each candidate node the plate covers,
``side (z - height) >= 0``: the Newton solver (`fem.engine.solver.newton`) projects its iterates onto
the bounds and holds a node on the plate while the plate pushes it (an active set with the
sign of the multiplier checked every iteration). There is no penalty: nodes never penetrate and
the tangent is not polluted by penalty stiffness. The contact force of a node is the multiplier
``lambda = side * dPi/dz`` (>= 0) of its bound at equilibrium.

Tangential contact is Coulomb friction with the normal forces *lagged* from the last converged
load step and the slip measured from the position there (incremental, quasi-static). With
those fixed, friction derives from a convex potential (Li et al., "Incremental Potential
Contact", 2020):

    D(x) = sum_i mu lambda_i eps f0(|s_i| / eps),   s_i = (x_i, y_i) - (x_i, y_i)_last,
    f0(r) = r^2 - r^3 / 3 (r < 1),   r - 1/3 (r >= 1),

so the friction force ``mu lambda_i f1(|s_i|/eps)`` (``f1 = f0'``: ``2 r - r^2``, then 1) grows
smoothly from stick to the Coulomb limit ``mu lambda_i`` over a slip of ``eps``, and energy,
force and a symmetric positive semi-definite tangent fit the same Newton iteration as the
tissue. The lag costs nothing in a steady slide and is one step behind while the normal force
changes, which over tens of recorded steps is small.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

Z_AXIS = 2  #: cranio-caudal axis
Y_AXIS = 1  #: anteroposterior axis
TANGENTIAL = (0, 1)  #: the plate's in-plane axes (x, y)


def friction_mollifier(r: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """``f0(r)``, ``f1(r) = f0'(r)`` and ``f1'(r)`` of the stick-slip transition (C2 at r = 1).

    Parameters
    ----------
    r : array
        Slip over the regularisation length, ``|s| / eps`` (>= 0).
    """
    r = np.asarray(r, float)
    stick = r < 1.0
    f0 = np.where(stick, r**2 - r**3 / 3.0, r - 1.0 / 3.0)
    f1 = np.where(stick, 2.0 * r - r**2, 1.0)
    df1 = np.where(stick, 2.0 - 2.0 * r, 0.0)
    return f0, f1, df1


@dataclass
class RigidPlate:
    """A rigid plate perpendicular to z: a bound on its candidate nodes, and their friction.

    Parameters
    ----------
    nodes : (M,) int
        Candidate nodes (the skin).
    height : float
        z of the plate surface, mm (moved by the compression driver).
    side : int
        +1 lower plate (body above), -1 upper plate (body below).
    chest_edge : float
        y of the plate's chest-side edge, mm; nodes with ``y < chest_edge`` are behind it.
    n_nodes : int
        Number of mesh nodes (the force vector has ``3 n_nodes`` entries).
    friction : float
        Coulomb coefficient (0: frictionless).
    slip_regularization : float
        ``eps``, mm: the slip over which friction rises from 0 to the Coulomb limit (like the
        elastic slip of ABAQUS' penalty friction, 0.5 % of a typical element length; 0.01 mm
        took 1.7x the Newton iterations on a breast, 0.1 mm is a tenth of a millimetre of
        stick compliance on centimetres of plate travel).
    """

    nodes: NDArray
    height: float
    side: int
    chest_edge: float
    n_nodes: int
    friction: float = 0.0
    slip_regularization: float = 0.1
    normal_force: NDArray = field(init=False, repr=False)
    anchor: NDArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.side not in (1, -1):
            raise ValueError(f"side must be +1 (lower plate) or -1 (upper plate), got {self.side}")
        if self.friction < 0:
            raise ValueError(f"friction coefficient must be >= 0, got {self.friction}")
        self.nodes = np.asarray(self.nodes, np.int64)
        self.normal_force = np.zeros(len(self.nodes))
        self.anchor = np.zeros((len(self.nodes), 2))
        self._z = 3 * self.nodes + Z_AXIS
        self._t = 3 * self.nodes[:, None] + np.array(TANGENTIAL)  # (M, 2) tangential DOFs

    # -- normal contact: bounds and multipliers ---------------------------------------------
    def covered(self, x: NDArray) -> NDArray[np.bool_]:
        """Which candidate nodes lie in front of the chest-side edge, (M,) bool."""
        return x[self.nodes, Y_AXIS] >= self.chest_edge

    def apply_bounds(self, x: NDArray, lower: NDArray, upper: NDArray) -> None:
        """Tighten the DOF bounds ``lower``/``upper`` (3N,) with this plate, in place."""
        dofs = self._z[self.covered(x)]
        if self.side > 0:
            lower[dofs] = np.maximum(lower[dofs], self.height)
        else:
            upper[dofs] = np.minimum(upper[dofs], self.height)

    def penetration(self, x: NDArray) -> NDArray[np.float64]:
        """``side (height - z)`` of each candidate node, mm (positive: inside the plate)."""
        return self.side * (self.height - x[self.nodes, Z_AXIS])

    def contact_forces(self, x: NDArray, gradient: NDArray) -> NDArray[np.float64]:
        """Normal force of each candidate node, Pa mm^2, (M,): the multiplier of its bound.

        ``gradient`` is ``dPi/dx`` (3N,) at equilibrium (internal minus external forces); a node
        on the plate carries ``side * gradient_z`` (the plate can only push), others nothing.
        """
        on_plate = self.covered(x) & (self.penetration(x) >= -1e-9)
        return np.where(on_plate, np.maximum(self.side * gradient[self._z], 0.0), 0.0)

    def reaction(self, x: NDArray, gradient: NDArray) -> float:
        """Total normal force of the plate on the body, Pa mm^2 (along ``side * z``)."""
        return float(self.contact_forces(x, gradient).sum())

    def accept(self, x: NDArray, gradient: NDArray) -> None:
        """Start a new load step from the converged ``x``: lag its normal forces, anchor slip."""
        self.normal_force = self.contact_forces(x, gradient)
        self.anchor = x[self.nodes][:, TANGENTIAL].copy()

    # -- friction: energy, force, tangent ---------------------------------------------------
    def _slip(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        s = x[self.nodes][:, TANGENTIAL] - self.anchor  # (M, 2)
        norm = np.linalg.norm(s, axis=1)
        return s, norm, self.friction * self.normal_force  # limit forces (M,)

    def energy(self, x: NDArray) -> float:
        """Friction potential ``D(x)``, Pa mm^3."""
        if self.friction == 0:
            return 0.0
        _, norm, limit = self._slip(x)
        eps = self.slip_regularization
        return float(limit @ (eps * friction_mollifier(norm / eps)[0]))

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dD/dx`` (3N,): each node's friction force opposes its slip, at most ``mu lambda``."""
        f = np.zeros(3 * self.n_nodes)
        if self.friction == 0:
            return f
        s, norm, limit = self._slip(x)
        eps = self.slip_regularization
        r = norm / eps
        _, f1, _ = friction_mollifier(r)
        # f1(r) / |s| -> 2 / eps as the slip vanishes.
        scale = np.where(r > 1e-12, f1 / np.maximum(norm, 1e-300), 2.0 / eps)
        np.add.at(f, self._t, (limit * scale)[:, None] * s)
        return f

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2D/dx2`` (3N, 3N): 2 x 2 blocks, ``mu lambda [f1'/eps n n^T + f1/|s| (I - n n^T)]``."""
        n = 3 * self.n_nodes
        if self.friction == 0:
            return sparse.csr_matrix((n, n))
        s, norm, limit = self._slip(x)
        eps = self.slip_regularization
        r = norm / eps
        _, f1, df1 = friction_mollifier(r)
        moving = r > 1e-12
        unit = np.where(moving[:, None], s / np.maximum(norm, 1e-300)[:, None], 0.0)
        radial = np.where(moving, df1 / eps, 2.0 / eps)
        hoop = np.where(moving, f1 / np.maximum(norm, 1e-300), 2.0 / eps)
        nn = unit[:, :, None] * unit[:, None, :]
        blocks = limit[:, None, None] * (
            radial[:, None, None] * nn + hoop[:, None, None] * (np.eye(2) - nn)
        )
        rows = np.repeat(self._t, 2, axis=1).ravel()
        cols = np.tile(self._t, (1, 2)).ravel()
        return sparse.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n, n))
