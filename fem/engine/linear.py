"""Sparse direct solvers for Newton's linear systems, chosen by size.

The tangents are symmetric; held DOFs keep their rows and columns with only the diagonal
(`constrained`), so the pattern of a load path's systems never changes.

* SuperLU (SciPy) with a minimum-degree ordering on ``K + K^T`` and no pivoting (26 % less
  fill than partial pivoting on a breast), partial pivoting as the fallback: no dependency,
  factorizes the condensed tangent; its ordering scales badly with 3-D meshes (a
  nested-refined breast of 17,400 tetrahedra, 11,235 DOFs: 1.7-4 s per factorization, 18 M
  nonzeros in the factors).
* MKL PARDISO (the optional ``mkl`` wheel, x86-64: ``pip install -e ".[pardiso]"``):
  symmetric indefinite LDL^T with METIS nested dissection, Bunch-Kaufman pivoting and
  iterative refinement; the ordering and symbolic analysis are done once per pattern
  (PARDISO phase 11) and reused by every later factorization (phase 22). A nodal-averaged
  tangent (`fem.engine.assembly.SplitTangent`) is factorized in its augmented, 1-ring form
  (a third more unknowns, 40 % of the nonzeros, 3x faster on a 139k-tetrahedra breast).

`resolve_backend` picks PARDISO from `PARDISO_FROM` DOFs on when MKL can be loaded (with the
augmented form it is faster from the paper-resolution cohort's 1,800 DOFs on: both steps of a
breast 25-30 % faster than with SuperLU, positions within 5e-7 mm), SuperLU otherwise;
`fem.engine.solver.ReusedFactorization` uses it (docs/benchmarks.md, "Real-size meshes").
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys
import weakref
from ctypes.util import find_library
from functools import cache

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.linalg import splu

from fem.engine.assembly import SplitTangent, same_pattern

#: DOFs from which ``auto`` prefers PARDISO (when MKL is installed).
PARDISO_FROM = 1000

BACKENDS = ("auto", "superlu", "pardiso")


#: A tangent as the solvers take it.
Tangent = sparse.spmatrix | SplitTangent


def condensed(K: Tangent) -> sparse.csr_matrix:
    """``K`` as one CSR matrix (a `SplitTangent`'s ``local + factor^T factor``)."""
    return K.full() if isinstance(K, SplitTangent) else K.tocsr()


def submatrix(K: Tangent, keep: NDArray[np.bool_]) -> Tangent:
    """The rows and columns of the DOFs ``keep``."""
    return K.submatrix(keep) if isinstance(K, SplitTangent) else K.tocsr()[keep][:, keep]


def constrained(K: Tangent, keep: NDArray[np.bool_]) -> Tangent:
    """``K`` with the rows and columns of the DOFs not in ``keep`` zeroed but their diagonal kept.

    Solving with it leaves those DOFs unchanged (zero right-hand side) while the matrix keeps its
    shape and sparsity pattern, so one factorization can precondition the next active set. A
    `SplitTangent` keeps the held DOFs' diagonal in ``local`` and their factor columns as
    explicit zeros.
    """
    if isinstance(K, SplitTangent):
        factor = K.factor.copy()
        factor.data *= keep[factor.indices]
        return SplitTangent(constrained(K.local, keep), factor)
    K = K.tocsr(copy=True)
    rows = np.repeat(np.arange(K.shape[0]), np.diff(K.indptr))
    K.data *= (keep[rows] & keep[K.indices]) | (rows == K.indices)
    return K


def add_diagonal(K: Tangent, d: NDArray) -> Tangent:
    """``K + diag(d)`` (a `SplitTangent`'s ``local`` gets it)."""
    if isinstance(K, SplitTangent):
        return SplitTangent((K.local + sparse.diags(d)).tocsr(), K.factor)
    return (K + sparse.diags(d)).tocsr()


def factorize(K: Tangent, backend: str = "auto"):  # SuperLU or PardisoFactor: .solve, .shape
    """A factorization of ``K`` by ``backend`` (`resolve_backend`), with its own PARDISO
    instance."""
    if resolve_backend(backend, K.shape[0]) == "superlu":
        return superlu(K)
    return Pardiso().factorize(K)


def superlu(K: Tangent) -> sparse.linalg.SuperLU:
    """Sparse LU of a symmetric matrix (a `SplitTangent` condensed): no pivoting first, partial
    pivoting if that fails."""
    K = condensed(K).tocsc()
    try:
        return splu(
            K, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True, "DiagPivotThresh": 0.0}
        )
    except RuntimeError:  # a zero pivot: indefinite or singular without pivoting
        return splu(K, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})


@cache
def mkl_pardiso() -> ctypes._CFuncPtr | None:
    """MKL's ``pardiso`` entry point, or None when no ``mkl_rt`` library can be loaded (looked
    up as `ctypes.util.find_library` does, then under ``sys.prefix/lib``, where the ``mkl``
    wheel puts it; ``PARDISO_MKL_RT`` names a file)."""
    candidates = [os.environ.get("PARDISO_MKL_RT"), find_library("mkl_rt")]
    candidates += sorted(glob.glob(f"{sys.prefix}/lib/libmkl_rt.so*"), key=len)
    for path in filter(None, candidates):
        try:
            function = ctypes.CDLL(path).pardiso
        except (OSError, AttributeError):
            continue
        int_p = ctypes.POINTER(ctypes.c_int32)
        function.argtypes = [ctypes.POINTER(ctypes.c_int64)] + [int_p] * 5 + [ctypes.c_void_p]
        function.argtypes += [int_p] * 6 + [ctypes.c_void_p] * 2 + [int_p]
        function.restype = None
        return function
    return None


def pardiso_phase(
    function: ctypes._CFuncPtr,
    handle: NDArray,
    iparm: NDArray,
    phase: int,
    upper: sparse.csr_matrix | None = None,
    b: NDArray | None = None,
) -> NDArray | None:
    """One call of MKL's ``pardiso`` (real symmetric indefinite) on the instance ``handle``
    (64 pointers) with the upper triangle ``upper`` (int32 CSR, zero-based); returns the
    solution of ``b`` (n,) or (n, k) for phase 33, None otherwise. Phase -1 (release) needs no
    matrix."""
    n = 0 if upper is None else upper.shape[0]
    rhs = np.zeros((1, n)) if b is None else np.asarray(b, float).reshape(n, -1).T.copy()
    x = np.zeros_like(rhs)
    error = ctypes.c_int32(0)
    int_p = ctypes.POINTER(ctypes.c_int32)

    def i32(v: int) -> ctypes._Pointer:
        return ctypes.byref(ctypes.c_int32(v))

    function(
        handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
        i32(1),  # maxfct
        i32(1),  # mnum
        i32(Pardiso.MTYPE),
        i32(phase),
        i32(n),
        None if upper is None else upper.data.ctypes.data,
        None if upper is None else upper.indptr.ctypes.data_as(int_p),
        None if upper is None else upper.indices.ctypes.data_as(int_p),
        None,  # perm
        i32(rhs.shape[0]),  # nrhs
        iparm.ctypes.data_as(int_p),
        i32(0),  # msglvl
        rhs.ctypes.data,
        x.ctypes.data,
        ctypes.byref(error),
    )
    if error.value:
        raise RuntimeError(f"PARDISO phase {phase} failed with error {error.value}")
    return None if b is None else x.T.reshape(np.shape(b))


class Pardiso:
    """One MKL PARDISO instance (real symmetric indefinite, ``mtype = -2``) for a sequence of
    matrices: the analysis of a pattern is kept until another pattern comes.

    Raises
    ------
    ImportError
        MKL cannot be loaded.
    """

    MTYPE = -2

    def __init__(self) -> None:
        self._pardiso = mkl_pardiso()
        if self._pardiso is None:
            raise ImportError(
                "MKL PARDISO needs the mkl wheel (pip install -e '.[pardiso]', x86-64 only)"
            )
        self._handle = np.zeros(64, np.int64)  # PARDISO's internal memory pointers
        self._iparm = np.zeros(64, np.int32)
        self._iparm[[0, 1, 9, 20, 34]] = (1, 2, 8, 1, 1)  # own settings, METIS, eps 1e-8,
        # Bunch-Kaufman pivoting, zero-based indices
        self._iparm[7] = 0  # iterative refinement only after perturbed pivots (2 steps)
        self._pattern: tuple[NDArray, NDArray] | None = None
        self._upper: sparse.csr_matrix | None = None
        self.analyses = 0
        weakref.finalize(self, pardiso_phase, self._pardiso, self._handle, self._iparm, -1)

    def _call(self, phase: int, b: NDArray | None = None) -> NDArray | None:
        return pardiso_phase(self._pardiso, self._handle, self._iparm, phase, self._upper, b)

    def factorize(self, K: Tangent) -> PardisoFactor:
        """Factorize a symmetric ``K`` (a `SplitTangent` in its augmented form); the analysis
        is redone only for a new pattern."""
        A = K.augmented() if isinstance(K, SplitTangent) else K
        upper = sparse.triu(A, format="csr")
        upper.sort_indices()
        upper.indptr = upper.indptr.astype(np.int32)
        upper.indices = upper.indices.astype(np.int32)
        self._upper = upper
        if not same_pattern(self._pattern, upper):
            if self._pattern is not None:
                self._call(-1)  # release the old analysis
            self._call(11)
            self._pattern = (upper.indptr.copy(), upper.indices.copy())
            self.analyses += 1
        self._call(22)
        return PardisoFactor(self, K.shape, upper.shape[0])

    def release(self) -> None:
        """Free PARDISO's memory of this instance (also done when it is garbage collected)."""
        if self._pattern is not None:
            self._call(-1)
            self._pattern = None


class PardisoFactor:
    """The current factorization of a `Pardiso` instance: ``solve(b)`` for (n,) or (n, k);
    an augmented system (``size`` > n) gets zeros appended to ``b`` and its first n rows
    returned."""

    def __init__(self, solver: Pardiso, shape: tuple[int, int], size: int) -> None:
        self.solver, self.shape, self.size = solver, shape, size

    def solve(self, b: NDArray) -> NDArray[np.float64]:
        b = np.asarray(b, float)
        n = self.shape[0]
        if self.size == n:
            return self.solver._call(33, b)
        padded = np.zeros((self.size, *b.shape[1:]))
        padded[:n] = b
        return self.solver._call(33, padded)[:n]


def resolve_backend(backend: str, n: int) -> str:
    """The backend used for ``n`` DOFs: ``auto`` is PARDISO from `PARDISO_FROM` DOFs on when
    MKL loads, SuperLU otherwise.

    Raises
    ------
    ValueError
        An unknown backend.
    """
    if backend not in BACKENDS:
        raise ValueError(f"linear_solver must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "pardiso" if n >= PARDISO_FROM and mkl_pardiso() is not None else "superlu"
    return backend
