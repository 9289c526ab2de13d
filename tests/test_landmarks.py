"""Landmarks: located in the imaged mesh, carried through a deformation, projected CC."""

import numpy as np
import pytest

from fem.contract.landmarks import carry, locate, project_cc


def test_landmarks_follow_an_affine_deformation_exactly(breast_mesh):
    points, cells = breast_mesh.points, breast_mesh.cells
    rng = np.random.default_rng(0)
    # Queries: element centroids and random points inside random elements.
    e = rng.integers(0, len(cells), 50)
    w = rng.dirichlet(np.ones(4), 50)
    queries = np.einsum("qkc,qk->qc", points[cells[e]], w)
    cell, weights = locate(points, cells, queries)
    assert (cell >= 0).all()
    np.testing.assert_allclose(weights.sum(1), 1.0)
    np.testing.assert_allclose(carry(points, cells, cell, weights), queries, atol=1e-9)
    A = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, -0.1], [0.05, 0.0, 0.6]])
    b = np.array([3.0, -2.0, 5.0])
    steps = np.stack([points @ (np.eye(3) + s * (A - np.eye(3))).T + s * b for s in (0.5, 1)])
    moved = carry(steps, cells, cell, weights)  # (2, Q, 3)
    np.testing.assert_allclose(moved[-1], queries @ A.T + b, atol=1e-9)
    assert moved.shape == (2, 50, 3)


def test_a_node_is_its_own_landmark_and_outside_points_are_marked(breast_mesh):
    points, cells = breast_mesh.points, breast_mesh.cells
    node = cells[7, 2]
    far = points.max(0) + 50.0
    cell, weights = locate(points, cells, np.stack([points[node], far]))
    assert cell[1] == -1 and np.isnan(weights[1]).all()
    np.testing.assert_allclose(
        carry(points, cells, cell[:1], weights[:1]), points[[node]], atol=1e-9
    )


def test_cc_projection_magnifies_about_the_source_foot():
    source = (10.0, 0.0)
    p = np.array([[10.0, 0.0, 30.0], [20.0, 40.0, 0.0], [20.0, 40.0, 50.0]])
    uv = project_cc(p, detector_z=0.0, source_xy=source, source_to_image=650.0)
    np.testing.assert_allclose(uv[0], source)  # on the central ray
    np.testing.assert_allclose(uv[1], [20.0, 40.0])  # on the detector
    np.testing.assert_allclose(uv[2], np.array(source) + [10.0, 40.0] * np.array(650 / 600))
    np.testing.assert_allclose(project_cc(p, 0.0, source, None), p[:, :2])
    with pytest.raises(ValueError, match="above the X-ray source"):
        project_cc([[0.0, 0.0, 700.0]], 0.0, source)
