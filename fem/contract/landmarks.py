"""Points inside a tetrahedral mesh carried through its deformation, and their mammogram.

A landmark (say a lesion seen on MRI) is located once in the imaged mesh: its containing
tetrahedron and barycentric coordinates. Any deformed state of the mesh (a predicted unloaded
or compressed shape) then carries it along with the same linear interpolation as the FE
displacement field. The cranio-caudal (CC) view projects points from an X-ray point source
above the breast onto the detector under the lower plate.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: Source-to-image distance of a mammography unit, mm (typical 650-660 mm).
SOURCE_TO_IMAGE_MM = 650.0


def barycentric_coordinates(
    points: NDArray, cells: NDArray, queries: NDArray
) -> NDArray[np.float64]:
    """Barycentric coordinates of every query in every tetrahedron.

    Parameters
    ----------
    points : (N, 3)
        Node coordinates, mm.
    cells : (E, 4)
        Tetrahedra.
    queries : (Q, 3)
        Points, mm.

    Returns
    -------
    (Q, E, 4) float64 ; a query lies in a tetrahedron when all four are >= 0.
    """
    p = points[cells]  # (E, 4, 3)
    edges = (p[:, 1:] - p[:, :1]).transpose(0, 2, 1)  # (E, 3, 3): columns p_i - p_0
    inverse = np.linalg.inv(edges)  # (E, 3, 3)
    d = queries[:, None, :] - p[None, :, 0]  # (Q, E, 3)
    lam = np.einsum("eij,qej->qei", inverse, d)  # (Q, E, 3)
    return np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)


def locate(
    points: NDArray, cells: NDArray, queries: NDArray, tol: float = 1e-9, chunk: int = 256
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The tetrahedron that contains each query, and the query's barycentric coordinates in it.

    Returns
    -------
    cell : (Q,) int64
        Index of the containing tetrahedron; -1 for a query outside the mesh.
    weights : (Q, 4) float64
        Barycentric coordinates (NaN outside the mesh).
    """
    queries = np.atleast_2d(np.asarray(queries, float))
    cell = np.full(len(queries), -1, np.int64)
    weights = np.full((len(queries), 4), np.nan)
    for start in range(0, len(queries), chunk):
        lam = barycentric_coordinates(points, cells, queries[start : start + chunk])
        worst = lam.min(-1)  # (q, E): most negative coordinate
        best = worst.argmax(1)  # the tetrahedron the query is most inside of
        inside = worst[np.arange(len(best)), best] >= -tol
        rows = start + np.flatnonzero(inside)
        cell[rows] = best[inside]
        weights[rows] = lam[np.flatnonzero(inside), best[inside]]
    return cell, weights


def carry(positions: NDArray, cells: NDArray, cell: NDArray, weights: NDArray) -> NDArray:
    """Landmarks located by `locate` in deformed node ``positions`` (..., N, 3) -> (..., Q, 3)."""
    corners = positions[..., cells[cell], :]  # (..., Q, 4, 3)
    return np.einsum("...qkc,qk->...qc", corners, weights)


def project_cc(
    points: NDArray,
    detector_z: float,
    source_xy: tuple[float, float],
    source_to_image: float | None = SOURCE_TO_IMAGE_MM,
) -> NDArray[np.float64]:
    """Cranio-caudal projection onto the detector plane ``z = detector_z`` (mm).

    The X-ray point source sits ``source_to_image`` mm above the detector at ``source_xy``
    (x, y): a point at height h above the detector is magnified by ``SID / (SID - h)`` about
    the source's foot point. ``source_to_image=None`` projects in parallel (along -z).

    Returns
    -------
    (..., 2) detector coordinates (x, y), mm.
    """
    points = np.asarray(points, float)
    if source_to_image is None:
        return points[..., :2].copy()
    height = points[..., 2] - detector_z
    if np.any(height >= source_to_image):
        raise ValueError("a point lies at or above the X-ray source")
    foot = np.asarray(source_xy, float)
    return (
        foot + (points[..., :2] - foot) * (source_to_image / (source_to_image - height))[..., None]
    )
