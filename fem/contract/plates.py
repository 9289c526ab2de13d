"""Compression plates as frames: where a plate is, which side is inside it, what it covers.

A plate is a (3, 3) array of three rows, millimetres in the patient frame RAS+ (x right,
y anterior, z superior):

* row 0 ``origin``: a point of the plate surface on its chest-side edge, mm;
* row 1 ``normal``: unit normal of the plate surface, pointing from the plate into the breast
  (the lower cranio-caudal (CC) plate: (0, 0, +1); the upper CC plate: (0, 0, -1));
* row 2 ``axis``: unit vector in the plate plane, perpendicular to the chest-side edge,
  pointing away from the chest (CC: (0, 1, 0)); orthogonal to ``normal``.

The plate covers the points ``p`` with ``(p - origin) . axis >= 0`` (in front of its
chest-side edge); a covered point is inside the plate when ``(p - origin) . normal < 0``.
A trajectory stores its plates as (T2, 2, 3, 3): plate 0 is the lower (fixed, detector)
plate, plate 1 the upper (moving, paddle) plate (``docs/trajectory-schema.md``).

Pure geometry: NumPy only.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Row of each part of a plate frame.
ORIGIN, NORMAL, AXIS = 0, 1, 2

#: Tolerance of the unit-length and orthogonality checks of `check_plates`.
UNIT_TOLERANCE = 1e-6


def plate_basis(plate: ArrayLike) -> NDArray[np.float64]:
    """The rotation of a plate's frame: columns ``(b, axis, normal)``, ``b = axis x normal``.

    Coordinates in the plate frame are ``p' = basis.T @ p`` (rotation only, no translation):
    ``p'[1]`` is the distance along the plate's axis (away from the chest), ``p'[2]`` the
    height along its normal. For the lower CC plate (axis (0, 1, 0), normal (0, 0, 1)) the
    basis is exactly the identity.

    Parameters
    ----------
    plate : (3, 3) float
        One plate frame (origin, normal, axis rows), mm and unit vectors.

    Returns
    -------
    (3, 3) float64
        A rotation matrix (right-handed when normal and axis are orthonormal).
    """
    plate = np.asarray(plate, np.float64)
    normal, axis = plate[NORMAL], plate[AXIS]
    return np.stack([np.cross(axis, normal), axis, normal], axis=1)


def cc_plates(lower_edge_yz: ArrayLike, upper_edge_yz: ArrayLike) -> NDArray[np.float64]:
    """Cranio-caudal plate pairs from the (y, z) of their chest-side edges.

    Parameters
    ----------
    lower_edge_yz, upper_edge_yz : (..., 2) float
        (y, z) of the lower and the upper plate's chest-side edge, mm (broadcast together).

    Returns
    -------
    (..., 2, 3, 3) float64
        Plate pairs: origins (0, y, z), normals (0, 0, +1) (lower) and (0, 0, -1) (upper),
        axes (0, 1, 0).
    """
    lower, upper = np.broadcast_arrays(
        np.asarray(lower_edge_yz, np.float64), np.asarray(upper_edge_yz, np.float64)
    )
    out = np.zeros((*lower.shape[:-1], 2, 3, 3))
    for k, (edge, nz) in enumerate(((lower, 1.0), (upper, -1.0))):
        out[..., k, ORIGIN, 1:] = edge
        out[..., k, NORMAL, 2] = nz
        out[..., k, AXIS, 1] = 1.0
    return out


def upgrade_v1_plates(plates: ArrayLike) -> NDArray[np.float64]:
    """Schema version 1 plates, (y, z) of the CC plates' chest-side edges, as frames.

    Parameters
    ----------
    plates : (T, 2, 2) float
        (y, z) of the lower (0) and upper (1) plate's chest-side edge per step, mm.

    Returns
    -------
    (T, 2, 3, 3) float64
        `cc_plates` of them: origin (0, y, z), normal (0, 0, +1) for the lower and
        (0, 0, -1) for the upper plate, axis (0, 1, 0).
    """
    plates = np.asarray(plates, np.float64)
    if plates.ndim != 3 or plates.shape[1:] != (2, 2):
        raise ValueError(f"version-1 plates have shape (T, 2, 2), got {plates.shape}")
    return cc_plates(plates[:, 0], plates[:, 1])


def rotate_plates(plates: ArrayLike, rotation: ArrayLike) -> NDArray[np.float64]:
    """Plates (..., 3, 3) turned by ``rotation`` (3, 3) about the patient frame's origin:
    every row ``r`` (origin, normal, axis) becomes ``rotation @ r``."""
    return np.asarray(plates, np.float64) @ np.asarray(rotation, np.float64).T


def covered(points: ArrayLike, plate: ArrayLike) -> NDArray[np.bool_]:
    """Whether each point lies in front of the plate's chest-side edge (the plate covers it).

    Parameters
    ----------
    points : (N, 3) float
        Positions, mm.
    plate : (3, 3) float
        One plate frame.

    Returns
    -------
    (N,) bool
        ``(p - origin) . axis >= 0``.
    """
    plate = np.asarray(plate, np.float64)
    return (np.asarray(points, np.float64) - plate[ORIGIN]) @ plate[AXIS] >= 0


def penetration(points: ArrayLike, plate: ArrayLike) -> NDArray[np.float64]:
    """Signed depth of each point inside the plate's plane, mm.

    Parameters
    ----------
    points : (N, 3) float
        Positions, mm.
    plate : (3, 3) float
        One plate frame.

    Returns
    -------
    (N,) float64
        ``-(p - origin) . normal``: positive inside the plate (behind its surface), negative
        on the breast's side. Whether the plate covers the point is `covered`'s question.
    """
    plate = np.asarray(plate, np.float64)
    return -((np.asarray(points, np.float64) - plate[ORIGIN]) @ plate[NORMAL])


def check_plates(plates: NDArray, n_steps: int, source: str = "trajectory") -> None:
    """Refuse plates that are not (T2, 2, 3, 3) frames with unit, orthogonal normals and axes.

    Raises
    ------
    ValueError
        Naming ``source`` and the field ``'plates'``: wrong shape, non-finite values, a normal
        or axis not of unit length, or a normal not orthogonal to its axis (tolerance
        `UNIT_TOLERANCE`).
    """
    expected = (n_steps, 2, 3, 3)
    if plates.shape != expected:
        raise ValueError(f"{source}: field 'plates' must have shape {expected}, got {plates.shape}")
    if not np.isfinite(plates).all():
        raise ValueError(f"{source}: field 'plates' contains NaN or infinite values")
    for row, name in ((NORMAL, "normals"), (AXIS, "axes")):
        length = np.linalg.norm(plates[:, :, row], axis=-1)
        if (np.abs(length - 1.0) > UNIT_TOLERANCE).any():
            raise ValueError(
                f"{source}: field 'plates' has plate {name} that are not unit vectors "
                f"(lengths {length.min():.6g} .. {length.max():.6g})"
            )
    dot = np.abs((plates[:, :, NORMAL] * plates[:, :, AXIS]).sum(axis=-1))
    if (dot > UNIT_TOLERANCE).any():
        raise ValueError(
            f"{source}: field 'plates' has a plate whose normal and axis are not orthogonal "
            f"(|normal . axis| up to {dot.max():.3g})"
        )
