"""The element kernel: derivatives, the scikit-fem reference, patch test, rigid motion."""

import numpy as np
import pytest
from conftest import assert_exact_derivatives
from scipy import sparse

from fem.breasts.mesh import bcc_lattice, compact_mesh
from fem.contract.quality import boundary_faces
from fem.engine.assembly import BlockPattern, HyperelasticBody, Model, skfem_tangent
from fem.engine.material import lame_parameters, neo_hookean_pk1
from fem.engine.membrane import SkinMembrane


@pytest.fixture(scope="module")
def block():
    points, cells = bcc_lattice(np.zeros(3), np.full(3, 20.0), 5.0)
    points, cells = compact_mesh(points, cells)
    mu, kappa = lame_parameters(np.where(np.arange(len(cells)) % 3 == 0, 2500.0, 1100.0), 0.495)
    return points, cells, mu, kappa


@pytest.mark.parametrize(
    ("averaging", "stabilization"), [("element", 0.0), ("nodal", 0.0), ("nodal", 0.1)]
)
def test_force_and_tangent_are_derivatives(block, averaging, stabilization):
    points, cells, mu, kappa = block
    body = HyperelasticBody(points, cells, mu, kappa, averaging, stabilization)
    x = points + 0.4 * np.random.default_rng(0).standard_normal(points.shape)
    assert_exact_derivatives(body, x)


def test_fast_kernel_equals_scikit_fem(block):
    points, cells, mu, kappa = block
    body = HyperelasticBody(points, cells, mu, kappa, averaging="element")
    x = points + 0.3 * np.random.default_rng(2).standard_normal(points.shape)
    K, K_ref = body.tangent(x), skfem_tangent(body, x)
    assert abs(K - K_ref).max() <= 1e-12 * abs(K_ref).max()


@pytest.mark.parametrize("averaging", ["element", "nodal"])
def test_patch_test_homogeneous_deformation(block, averaging):
    """An affine deformation gives equal stress everywhere: interior nodes are in equilibrium
    and the boundary forces equal the exact traction resultants P N A."""
    points, cells, _, _ = block
    body = HyperelasticBody(points, cells, 1100.0 / 2.99, 1100.0 / 0.03, averaging=averaging)
    F = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.05], [0.1, 0.0, 1.05]])
    f = body.internal_force(points @ F.T).reshape(-1, 3)
    faces, _ = boundary_faces(points, cells)
    interior = np.setdiff1d(np.arange(len(points)), faces)
    assert interior.size > 10
    assert np.abs(f[interior]).max() < 1e-8 * np.abs(f).max()
    # Boundary nodes carry the traction resultants: a third of P N A of each boundary triangle.
    P = neo_hookean_pk1(F, 1100.0 / 2.99, 1100.0 / 0.03)
    p = points[faces]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    expected = np.zeros_like(f)
    for k in range(3):
        np.add.at(expected, faces[:, k], area_normal @ P.T / 3.0)
    np.testing.assert_allclose(f, expected, atol=1e-8 * np.abs(f).max())


@pytest.mark.parametrize("averaging", ["element", "nodal"])
def test_rigid_rotation_gives_zero_force(block, averaging):
    points, cells, mu, kappa = block
    body = HyperelasticBody(points, cells, mu, kappa, averaging=averaging)
    a = 0.9
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    x = points @ R.T + np.array([3.0, -2.0, 1.0])
    assert body.energy(x) == pytest.approx(0, abs=1e-6)
    assert np.abs(body.internal_force(x)).max() < 1e-8


def test_stabilization_interpolates_between_nodal_and_element(block):
    points, cells, mu, kappa = block
    x = points + 0.4 * np.random.default_rng(5).standard_normal(points.shape)
    nodal = HyperelasticBody(points, cells, mu, kappa, "nodal").energy(x)
    element = HyperelasticBody(points, cells, mu, kappa, "element").energy(x)
    iso = HyperelasticBody(points, cells, mu, 0 * kappa, "element").energy(x)
    mixed = HyperelasticBody(points, cells, mu, kappa, "nodal", 0.25).energy(x)
    assert mixed - iso == pytest.approx(0.75 * (nodal - iso) + 0.25 * (element - iso), rel=1e-10)
    with pytest.raises(ValueError, match="stabilization"):
        HyperelasticBody(points, cells, mu, kappa, "nodal", 1.5)


@pytest.mark.parametrize("stabilization", [0.0, 0.1])
def test_model_tangent_in_one_pattern_equals_the_sum_of_its_parts(block, stabilization):
    """`Model.tangent` scatters every part into one `BlockPattern` and keeps nodal averaging's
    coupling as a factor: ``local + factor^T factor`` is the same matrix as adding each part's
    own sparse tangent; ``local`` has full 3 x 3 node blocks and a fixed pattern."""
    points, cells, mu, kappa = block
    body = HyperelasticBody(points, cells, mu, kappa, "nodal", stabilization)
    skin = SkinMembrane(points, boundary_faces(points, cells)[0], mu=300.0)
    model = Model(body, (skin,))
    x = points + 0.3 * np.random.default_rng(4).standard_normal(points.shape)
    expected = body.tangent(x) + skin.tangent(x)
    K = model.tangent(x)
    assert abs(K.full() - expected).max() <= 1e-12 * abs(expected).max()
    v = np.random.default_rng(5).standard_normal(K.shape[0])
    np.testing.assert_allclose(
        K @ v, expected @ v, rtol=1e-12, atol=1e-12 * abs(expected @ v).max()
    )
    np.testing.assert_allclose(K.diagonal(), expected.diagonal(), rtol=1e-12)
    assert K.factor.shape == (len(points), 3 * len(points))  # the nodal patches only
    local = K.local
    assert local.has_sorted_indices and np.all(np.diff(local.indptr)[::3] % 3 == 0)
    assert model.tangent(x + 0.1).local.nnz == local.nnz  # the pattern is fixed
    assert local.nnz < 0.6 * expected.nnz  # the 1-ring stencil


def test_augmented_tangent_solves_the_condensed_system(block):
    """Eliminating the augmented system's patch unknowns gives the condensed tangent: its
    first n unknowns solve ``(local + factor^T factor) u = b``; plain P1 has no factor."""
    points, cells, mu, kappa = block
    x = points + 0.3 * np.random.default_rng(6).standard_normal(points.shape)
    fixed = np.repeat(points[:, 2] == 0.0, 3)
    K = Model(HyperelasticBody(points, cells, mu, kappa, "nodal", 0.1)).tangent(x)
    K = K.submatrix(~fixed)
    n = K.shape[0]
    b = np.random.default_rng(7).standard_normal(n)
    A = K.augmented()
    assert A.shape == (n + len(points), n + len(points))
    assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
    u = sparse.linalg.spsolve(A.tocsc(), np.concatenate([b, np.zeros(len(points))]))[:n]
    np.testing.assert_allclose(K.full() @ u, b, atol=1e-9 * np.abs(b).max())
    plain = Model(HyperelasticBody(points, cells, mu, kappa, "element")).tangent(x)
    assert plain.factor.shape[0] == 0 and plain.augmented().shape == plain.shape


def test_block_pattern_union_of_sets():
    """A pattern holds every set's blocks, overlapping ones once."""
    dofs = np.array([[0, 1], [4, 5]])
    pattern = BlockPattern(6, [dofs, np.array([[1, 4]])])
    data = np.zeros(pattern.nnz)
    pattern.scatter(data, 0, np.ones((2, 2, 2)))
    K = pattern.matrix(data).toarray()
    assert pattern.nnz == 10
    assert K[0, 1] == K[5, 4] == 1.0 and K[1, 4] == 0.0 and K.sum() == 8.0
