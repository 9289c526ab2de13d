"""Frictionless contact of surface nodes with rigid compression plates (smoothed penalty).

A plate is the plane ``z = height`` (cranio-caudal axis z) covering the region anterior to its
chest-side edge, ``y >= chest_edge``. The body lies above a lower plate (``side = +1``) and
below an upper plate (``side = -1``). For a candidate node with tributary skin area ``A`` the
penetration is ``d = side (height - z)`` and the stored energy is

    A k phi(d + d0),   phi(s) = 0 (s <= 0),  s^3 / (6 delta) (0 < s < delta),
                                 s^2 / 2 - delta s / 2 + delta^2 / 6 (s >= delta),

a C2 penalty (no chattering between active sets: the stiffness ``A k phi''`` ramps from 0 to
``A k`` over ``delta``). The small offset ``d0 = delta / 2`` makes a plate act from a gap of
``d0`` on, so that a body resting on a plate has contact stiffness from the first iteration.
At pressure ``p`` the penetration is ``p / k - d0 + O(delta)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

Z_AXIS = 2  #: cranio-caudal axis
Y_AXIS = 1  #: anteroposterior axis


def smooth_ramp(s: NDArray, delta: float) -> tuple[NDArray, NDArray, NDArray]:
    """``phi(s)``, ``phi'(s)`` and ``phi''(s)`` of the C2 penalty ramp of width ``delta``."""
    s = np.asarray(s, float)
    lo, hi = s <= 0, s >= delta
    mid = ~lo & ~hi
    phi, d1, d2 = np.zeros_like(s), np.zeros_like(s), np.zeros_like(s)
    phi[mid], d1[mid], d2[mid] = (
        s[mid] ** 3 / (6 * delta),
        s[mid] ** 2 / (2 * delta),
        s[mid] / delta,
    )
    phi[hi] = s[hi] ** 2 / 2 - delta * s[hi] / 2 + delta**2 / 6
    d1[hi], d2[hi] = s[hi] - delta / 2, 1.0
    return phi, d1, d2


def nodal_areas(points: NDArray, triangles: NDArray) -> NDArray[np.float64]:
    """Tributary area of each node: a third of each incident triangle's area, shape (N,)."""
    p = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    out = np.zeros(len(points))
    np.add.at(out, triangles.ravel(), np.repeat(area / 3.0, 3))
    return out


@dataclass
class PlateContact:
    """Penalty contact of ``nodes`` with one rigid plate.

    Parameters
    ----------
    nodes : (M,) int
        Candidate nodes.
    areas : (M,) float
        Their tributary areas, mm^2.
    height : float
        z of the plate surface, mm (changed by the compression driver).
    side : int
        +1 lower plate (body above), -1 upper plate (body below).
    chest_edge : float
        y of the plate's chest-side edge; nodes with ``y < chest_edge`` are behind the plate.
    stiffness : float
        Penalty per unit area, Pa/mm.
    smoothing : float
        Width ``delta`` of the C2 ramp, mm.
    n_nodes : int
        Total number of mesh nodes (size of the force vector / 3).
    """

    nodes: NDArray
    areas: NDArray
    height: float
    side: int
    chest_edge: float
    n_nodes: int
    stiffness: float = 2e5
    smoothing: float = 0.05
    _dofs: NDArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.side not in (1, -1):
            raise ValueError(f"side must be +1 (lower plate) or -1 (upper plate), got {self.side}")
        self.nodes = np.asarray(self.nodes, np.int64)
        self.areas = np.asarray(self.areas, float)
        self._dofs = 3 * self.nodes + Z_AXIS

    def _ramp(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        z = x[self.nodes, Z_AXIS]
        covered = x[self.nodes, Y_AXIS] >= self.chest_edge
        s = self.side * (self.height - z) + 0.5 * self.smoothing
        phi, d1, d2 = smooth_ramp(s, self.smoothing)
        w = self.stiffness * self.areas * covered
        return w * phi, w * d1, w * d2

    def penetration(self, x: NDArray) -> NDArray[np.float64]:
        """``side (height - z)`` of each candidate node, mm (positive: inside the plate)."""
        return self.side * (self.height - x[self.nodes, Z_AXIS])

    def energy(self, x: NDArray) -> float:
        return float(self._ramp(x)[0].sum())

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dE/dx`` (3N,); the plate pushes the node away: ``-side * A k phi'``."""
        _, d1, _ = self._ramp(x)
        f = np.zeros(3 * self.n_nodes)
        np.add.at(f, self._dofs, -self.side * d1)
        return f

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        _, _, d2 = self._ramp(x)
        n = 3 * self.n_nodes
        return sparse.csr_matrix((d2, (self._dofs, self._dofs)), shape=(n, n))

    def reaction(self, x: NDArray) -> float:
        """Total normal force the plate exerts on the body, Pa mm^2 (along ``side * z``)."""
        return float(self._ramp(x)[1].sum())
