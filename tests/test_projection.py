"""The projection onto valid shapes: no inverted element, no node inside a plate, the whole
volume in range, held directions kept."""

import numpy as np
import pytest
import skfem

from fem.contract import projection
from fem.contract.plates import cc_plates, covered, penetration, rotate_plates
from fem.contract.projection import (
    ProjectionFailed,
    constraints,
    free_projectors,
    project,
    project_steps,
    project_valid,
    volume_gradients,
)
from fem.contract.quality import signed_volume


@pytest.fixture(scope="module")
def block() -> tuple[np.ndarray, np.ndarray]:
    """A 10 mm cube in 5 x 5 x 5 boxes of tetrahedra, right-handed: (points, cells)."""
    m = skfem.MeshTet.init_tensor(*(np.linspace(0.0, 10.0, 6),) * 3)
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return p, t


def test_volume_gradients_are_the_derivatives_of_the_signed_volume(block):
    p, t = block
    x = p + np.random.default_rng(0).normal(0, 0.3, p.shape)
    h = 1e-6
    for cell in t[:5]:
        g = volume_gradients(x, cell[None])[0]
        for a in range(4):
            for i in range(3):
                y = x.copy()
                y[cell[a], i] += h
                fd = (signed_volume(y, cell[None]) - signed_volume(x, cell[None]))[0] / h
                assert g[a, i] == pytest.approx(fd, abs=1e-5)


def test_a_deliberately_bad_shape_becomes_valid_and_a_valid_one_stays(block):
    p, t = block
    bad = p + np.random.default_rng(1).normal(0, 1.0, p.shape)  # noise of half an edge
    assert (signed_volume(bad, t) <= 0).sum() > 100
    out = project_valid(t, p, bad, min_volume_ratio=0.1, volume_change=(-0.01, 0.01))
    ratio = signed_volume(out.points, t) / signed_volume(p, t)
    assert ratio.min() >= 0.1 and out.min_volume_ratio == pytest.approx(ratio.min())
    assert -0.01 <= out.volume_change <= 0.01
    assert 0 < out.moved_rms_mm < 1.0  # less than the noise it undoes
    same = project_valid(t, p, p)
    assert same.sweeps == 0 and np.array_equal(same.points, p) and same.moved_max_mm == 0.0


def test_a_folded_mesh_against_held_nodes_is_unfolded(block, monkeypatch):
    """Noise of a whole edge with the bottom face held folds the mesh: the elements' averaged
    requests cancel and plain sweeps stall; the smoothing step after a stall unfolds it."""
    p, t = block
    bottom = np.flatnonzero(p[:, 2] == 0)
    held = (np.tile(bottom, 3), np.repeat(np.eye(3), len(bottom), axis=0))
    folded = p + np.random.default_rng(0).normal(0, 2.0, p.shape)
    settings = {"min_volume_ratio": 0.1, "volume_change": (-0.01, 0.01), "held": held}
    out = project_valid(t, p, folded, **settings)
    assert (signed_volume(out.points, t) / signed_volume(p, t)).min() >= 0.1
    assert np.array_equal(out.points[bottom], p[bottom])
    monkeypatch.setattr(projection, "STALL_SWEEPS", 10**9)  # no smoothing: the sweeps stall
    with pytest.raises(ProjectionFailed, match=r"elements below volume ratio 0\.1"):
        project_valid(t, p, folded, **settings)


def test_lost_volume_is_given_back_within_the_range(block):
    p, t = block
    shrunk = 5.0 + 0.95 * (p - 5.0)  # -14 % volume, no element inverted
    out = project_valid(t, p, shrunk, volume_change=(-0.01, 0.01))
    assert -0.01 <= out.volume_change <= 0.01
    assert (signed_volume(out.points, t) > 0).all()


def test_nodes_inside_a_plate_come_out_and_held_directions_hold(block):
    p, t = block
    plates = cc_plates([-1.0, 0.0], [-1.0, 9.0])  # the upper plate 1 mm into the cube
    skin = np.flatnonzero((p == 0).any(axis=1) | (p == 10).any(axis=1))
    x = p.copy()
    x[0, 2] = -0.5  # ... and one node through the lower plate
    held_node = skin[np.argmax(x[skin, 2])]  # a top node held in x and y: it moves in z only
    held = (np.array([held_node, held_node]), np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    out = project_valid(t, p, x, skin, plates, min_volume_ratio=0.05, held=held)
    for plate in plates:
        inside = covered(out.points[skin], plate) & (penetration(out.points[skin], plate) > 1e-6)
        assert not inside.any()
    assert out.max_penetration_mm <= 1e-6
    assert out.points[0, 2] == pytest.approx(0.0)
    np.testing.assert_array_equal(out.points[held_node, :2], x[held_node, :2])
    assert out.points[held_node, 2] == pytest.approx(9.0)
    assert (signed_volume(out.points, t) / signed_volume(p, t)).min() >= 0.05


def test_a_node_nearer_the_plate_edge_leaves_behind_it(block):
    """The upper plate covers y >= 9.5 and reaches 2 mm into the cube: the top nodes at y = 10
    are 0.5 mm in front of its chest-side edge face and 2 mm under its surface, so they leave
    behind the edge face (tissue bulging out behind the plate), not down onto the surface."""
    p, t = block
    plates = cc_plates([-1.0, -1.0], [9.5, 8.0])
    skin = np.flatnonzero((p == 0).any(axis=1) | (p == 10).any(axis=1))
    out = project_valid(t, p, p, skin, plates, min_volume_ratio=0.05)
    edge_row = (p[:, 1] == 10) & (p[:, 2] == 10)
    assert edge_row.sum() == 6
    back = 0.5 + projection.EDGE_CLEARANCE
    np.testing.assert_allclose(out.points[edge_row], p[edge_row] - [0.0, back, 0.0], atol=1e-9)
    assert not covered(out.points[edge_row].astype(np.float32), plates[1]).any()  # as written
    np.testing.assert_array_equal(out.points[~edge_row], p[~edge_row])
    assert out.moved_max_mm == pytest.approx(back) and out.max_penetration_mm == 0.0


@pytest.mark.parametrize("stall_sweeps", [projection.STALL_SWEEPS, 3])
def test_the_steps_of_a_trajectory_project_together_as_each_alone(block, monkeypatch, stall_sweeps):
    """`project_steps` sweeps all the invalid steps at once; each must come out as `project`
    makes it alone: a valid step, inverted elements, skin in a plate, two folds against the
    held bottom that stall at different sweeps (the smoothing; with stalls after 3 sweeps,
    several steps are smoothed in the same sweep), and a step without a valid shape."""
    monkeypatch.setattr(projection, "STALL_SWEEPS", stall_sweeps)
    p, t = block
    skin = np.flatnonzero((p == 0).any(axis=1) | (p == 10).any(axis=1))
    bottom = np.flatnonzero(p[:, 2] == 0)
    held = (np.tile(bottom, 3), np.repeat(np.eye(3), len(bottom), axis=0))
    c = constraints(t, p, skin, 0.1, (-0.01, 0.01), held, max_sweeps=300)
    pushed = p.copy()
    pushed[p[:, 2] == 10, 2] += 1.0  # the top face 1.5 mm into the upper plate at z = 9.5
    steps = np.stack(
        [
            p,
            p + np.random.default_rng(1).normal(0, 1.0, p.shape),  # inverted elements
            pushed,
            p + np.random.default_rng(3).normal(0, 1.5, p.shape),  # folds: stalls
            p + np.random.default_rng(7).normal(0, 1.5, p.shape),
            p,  # squeezed to a plane by its plates: no valid shape
        ]
    )
    a = np.radians(10.0)  # plates tilted about x, away from the block: each step its own normals
    tilt = np.array([[1.0, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    far = rotate_plates(cc_plates([-1.0, -10.0], [-1.0, 20.0]), tilt)
    plates = np.stack(
        [
            far,
            far,
            cc_plates([-1.0, 0.0], [-1.0, 9.5]),
            far,
            far,
            cc_plates([-1.0, 5.0], [-1.0, 5.0]),
        ]
    )
    smoothed = []
    smoothing_step = projection._smoothing_step
    monkeypatch.setattr(
        projection,
        "_smoothing_step",
        lambda x, *rest: smoothed.append(len(x)) or smoothing_step(x, *rest),
    )
    out = project_steps(c, steps, plates)
    assert smoothed and (out.sweeps[3:5] > stall_sweeps).all()
    if stall_sweeps == 3:
        assert max(smoothed) > 1  # several steps smoothed in one sweep
    assert out.sweeps[0] == 0 and (out.sweeps[1:5] > 0).all() and list(out.failed) == [5]
    for k, (x, plate) in enumerate(zip(steps, plates, strict=True)):
        try:
            alone = project(c, x, plate)
        except ProjectionFailed as exc:
            assert out.failed[k] == str(exc)
            np.testing.assert_array_equal(out.points[k], c.held(x))  # kept as given
            continue
        np.testing.assert_allclose(out.points[k], alone.points, rtol=0, atol=1e-9)
        assert out.sweeps[k] == alone.sweeps
        assert out.min_volume_ratio[k] == pytest.approx(alone.min_volume_ratio, abs=1e-12)
        assert out.moved_rms_mm[k] == pytest.approx(alone.moved_rms_mm, abs=1e-9)
        assert out.moved_max_mm[k] == pytest.approx(alone.moved_max_mm, abs=1e-9)


def test_free_projectors_remove_the_span_of_the_held_directions():
    s = np.sqrt(0.5)
    held = (
        np.array([0, 1, 1, 2, 2]),
        np.array([[0, 0, 1.0], [1, 0, 0], [s, s, 0], [1, 0, 0], [0, 1, 0]]),
    )
    P = free_projectors(4, held)
    np.testing.assert_allclose(P[0], np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    np.testing.assert_allclose(P[1], np.diag([0.0, 0.0, 1.0]), atol=1e-12)  # x and x+y: not z
    np.testing.assert_allclose(P[2], np.diag([0.0, 0.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(P[3], np.eye(3), atol=1e-12)


def test_an_impossible_shape_and_bad_settings_are_refused(block):
    p, t = block
    # both plates at z = 5 squeeze the whole surface into one plane: it encloses no volume
    skin = np.flatnonzero((p == 0).any(axis=1) | (p == 10).any(axis=1))
    plates = cc_plates([-1.0, 5.0], [-1.0, 5.0])
    with pytest.raises(ProjectionFailed, match=r"after 50 sweeps: \d+ elements below"):
        project_valid(t, p, p, skin, plates, max_sweeps=50)
    with pytest.raises(ValueError, match=r"points \(3, 3\) and reference"):
        project_valid(t, p, p[:3])
    with pytest.raises(ValueError, match="min_volume_ratio must lie in"):
        project_valid(t, p, p, min_volume_ratio=0.0)
    with pytest.raises(ValueError, match="plates and skin go together"):
        project_valid(t, p, p, plates=cc_plates([0.0, 0.0], [0.0, 10.0]))
    with pytest.raises(ValueError, match="volume_change must be"):
        project_valid(t, p, p, volume_change=(0.01, -0.01))
