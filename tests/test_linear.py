"""Sparse direct solvers by size: SuperLU always, MKL PARDISO where the mkl wheel is installed."""

import numpy as np
import pytest
from scipy import sparse

from fem.breasts.mesh import bcc_lattice, compact_mesh
from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.linear import (
    PARDISO_FROM,
    Pardiso,
    condensed,
    constrained,
    mkl_pardiso,
    resolve_backend,
    superlu,
)
from fem.engine.material import lame_parameters
from fem.engine.simulation import Simulation
from fem.engine.solver import damped_step

needs_mkl = pytest.mark.skipif(mkl_pardiso() is None, reason="the optional mkl wheel is absent")


@pytest.fixture(scope="module")
def tangent():
    """A nodal-averaged tangent of a deformed block with a face held (constrained pattern)."""
    points, cells = compact_mesh(*bcc_lattice(np.zeros(3), np.full(3, 20.0), 4.0))
    mu, kappa = lame_parameters(1100.0, 0.495)
    x = points + 0.2 * np.random.default_rng(0).standard_normal(points.shape)
    K = Model(HyperelasticBody(points, cells, mu, kappa)).tangent(x)
    keep = ~np.repeat(np.isclose(points[:, 2], 0.0), 3)
    return constrained(K, keep), keep


def test_backend_by_size():
    assert resolve_backend("auto", PARDISO_FROM - 1) == "superlu"
    assert resolve_backend("superlu", 10**6) == "superlu"
    expected = "pardiso" if mkl_pardiso() is not None else "superlu"
    assert resolve_backend("auto", PARDISO_FROM) == expected
    with pytest.raises(ValueError, match="linear_solver must be one of"):
        resolve_backend("umfpack", 10)
    with pytest.raises(ValueError, match=r"simulation\.linear_solver must be one of"):
        Simulation(linear_solver="cholmod")


@needs_mkl
def test_pardiso_solves_like_superlu_and_keeps_its_analysis(tangent):
    split, keep = tangent
    A = condensed(split)
    b = np.where(keep, np.random.default_rng(1).standard_normal(A.shape[0]), 0.0)
    solver = Pardiso()
    x = solver.factorize(A).solve(b)
    np.testing.assert_allclose(x, superlu(A).solve(b), rtol=0, atol=1e-9 * np.abs(x).max())
    B = np.stack([b, 2 * b], axis=1)
    expected = np.stack([x, 2 * x], axis=1) / 1.5
    np.testing.assert_allclose(
        solver.factorize(1.5 * A).solve(B), expected, atol=1e-9 * np.abs(x).max()
    )
    assert solver.analyses == 1  # the same pattern: numerical factorization only
    solver.factorize(A[:-3, :-3])
    assert solver.analyses == 2
    # The split tangent is factorized in its augmented form: the same solution.
    np.testing.assert_allclose(
        solver.factorize(split).solve(B)[:, 0], x, atol=1e-9 * np.abs(x).max()
    )
    assert solver.analyses == 3 and solver.factorize(split).shape == A.shape
    solver.release()


@pytest.mark.parametrize("backend", ["superlu", pytest.param("pardiso", marks=needs_mkl)])
def test_damped_step_solves_the_shifted_split_tangent(tangent, backend):
    """The Levenberg-Marquardt step of a split tangent, by either backend, is the solution of
    the condensed ``K + tau diag|K|`` with the held DOFs fixed."""
    split, keep = tangent
    r = np.random.default_rng(3).standard_normal(split.shape[0])
    d = damped_step(split, ~keep, r, 0.1, backend)
    K = condensed(split)
    A = constrained(K + 0.1 * sparse.diags(np.abs(K.diagonal())), keep)
    np.testing.assert_allclose(A @ d, -np.where(keep, r, 0.0), atol=1e-9 * np.abs(r).max())
    assert np.all(d[~keep] == 0.0)
