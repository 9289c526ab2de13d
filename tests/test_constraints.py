"""Held directions and node frames: the framed model is the same potential in other
coordinates, an oblique held direction holds exactly, and constraint files are read with
clear errors."""

import numpy as np
import pytest
from conftest import assert_exact_derivatives
from test_contact import KAPPA, MU, block, turn

from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.boundary import read_constraints
from fem.engine.constraints import FramedModel, HeldDirections, NodeFrames, equilibrium_path
from fem.engine.solver import DEFAULT_NEWTON, GRAVITY_FORCE_DENSITY, nodal_body_force


def oblique_frames(p):
    """The face x = 0 held along two oblique directions (its edge z = 0 along a third too:
    no sliding mode), another node along one more."""
    face = np.flatnonzero(np.isclose(p[:, 0], 0))
    d1, d2 = turn(30.0)[:, 0], np.array([0.0, 0.6, 0.8])
    held = HeldDirections(np.repeat(face, 2), np.tile([d1, d2], (len(face), 1)))
    edge = face[np.isclose(p[face, 2], 0)]
    d3 = np.cross(d1, d2)
    held = held + HeldDirections(edge, np.tile(d3 / np.linalg.norm(d3), (len(edge), 1)))
    held = held + HeldDirections(np.array([len(p) - 1]), np.array([[0.48, 0.6, 0.64]]))
    return NodeFrames.build(len(p), held), held


def test_frames_are_orthonormal_and_round_trip():
    p, _ = block()
    frames, _ = oblique_frames(p)
    R = frames.rotations
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", R, R), np.tile(np.eye(3), (len(p), 1, 1)), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    x = np.random.default_rng(0).standard_normal(p.shape)
    np.testing.assert_allclose(frames.to_global(frames.to_local(x)), x, atol=1e-12)
    face = np.isclose(p[:, 0], 0)
    assert frames.held.sum() == 2 * face.sum() + (face & np.isclose(p[:, 2], 0)).sum() + 1


def test_a_direction_nearly_in_a_coordinate_plane_gets_a_rotation():
    """A sliding-wall normal 6e-8 off the xy plane (a 2x remeshed cohort breast, P0107_L):
    one Gram-Schmidt pass let a fourth row through and the frame's determinant failed."""
    wall = np.array([[0.3446506223815562, -0.9387310309625447, 6.333254155892629e-08]])
    frames = NodeFrames.build(3, HeldDirections(np.array([1]), wall))
    R = frames.rotations[1]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 0], wall[0], atol=1e-15)  # the held direction first
    assert frames.held[1].tolist() == [True, False, False] and frames.rotated.tolist() == [1]


def test_framed_model_derivatives():
    p, t = block()
    frames, _ = oblique_frames(p)
    framed = FramedModel(Model(HyperelasticBody(p, t, MU, KAPPA)), frames)
    y = frames.to_local(p + np.random.default_rng(1).uniform(-0.5, 0.5, p.shape))
    assert_exact_derivatives(framed, y, eps=1e-6, rtol=1e-5)


def test_rotated_tangent_equals_the_sparse_product():
    """`NodeFrames.rotate` (in place on full 3 x 3 blocks) against ``T^T K T``; a pattern
    without full blocks is refused."""
    p, t = block()
    frames, _ = oblique_frames(p)
    x = p + 0.3 * np.random.default_rng(2).standard_normal(p.shape)
    K = Model(HyperelasticBody(p, t, MU, KAPPA)).tangent(x)
    T = frames.transform()
    expected = T.T @ K.local @ T
    assert (
        abs(frames.rotate(K.local, frames.rotation_plan(K.local)) - expected).max()
        <= 1e-12 * abs(expected).max()
    )
    factor = frames.rotate(K.factor, frames.rotation_plan(K.factor, rows=False))  # K T only
    assert abs(factor - K.factor @ T).max() <= 1e-12 * abs(K.factor).max()
    partial = Model(HyperelasticBody(p, t, MU, KAPPA)).tangent(p).local  # exact zeros at rest ...
    partial.eliminate_zeros()  # ... dropped
    with pytest.raises(ValueError, match="full 3 x 3 node blocks"):
        frames.rotation_plan(partial)


def test_direction_wise_constraint_holds_exactly():
    """A block hanging from its face x = 0 under oblique gravity, held along two oblique
    directions there (and one more node along a third): the held displacement components
    stay zero to round-off while the free ones move millimetres."""
    p, t = block()
    frames, held = oblique_frames(p)
    body = HyperelasticBody(p, t, MU, KAPPA)
    f = nodal_body_force(body, GRAVITY_FORCE_DENSITY * np.array([0.3, -0.5, -0.8]))
    x = equilibrium_path(Model(body), frames, p, lambda s: s * f, [0.5, 1.0], DEFAULT_NEWTON)[-1]
    u = x - p
    along = np.einsum("ij,ij->i", u[held.nodes], held.directions)
    assert np.abs(along).max() < 1e-10
    assert np.linalg.norm(u, axis=1).max() > 1.0


def test_read_constraints(tmp_path):
    good = tmp_path / "held.txt"
    good.write_text("# node axes\n3 xz\n5\n")
    held = read_constraints(good, 10)
    np.testing.assert_array_equal(held.nodes, [3, 3, 5, 5, 5])
    np.testing.assert_array_equal(held.directions[:2], [[1, 0, 0], [0, 0, 1]])
    for text, message in [
        ("3 xq\n", "line 1"),
        ("3 x y\n", "line 1"),
        ("12 x\n", r"\[0, 10\)"),
        ("\n", "no held nodes"),
    ]:
        bad = tmp_path / "bad.txt"
        bad.write_text(text)
        with pytest.raises(ValueError, match=message) as info:
            read_constraints(bad, 10)
        assert "bad.txt" in str(info.value) and "simulation.constraints" in str(info.value)
