"""Physical checks of predicted shapes: inverted elements, volume change, plate penetration."""

from dataclasses import replace

import numpy as np
import pytest
import skfem

from fem.contract.plates import cc_plates, rotate_plates
from fem.contract.projection import constraints
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from mammo_net import validity
from mammo_net.predictor import BreastShapes
from mammo_net.validity import (
    PhysicalChecks,
    PhysicallyImpossible,
    ValidityProjection,
    check_shape,
    check_shapes,
    plate_penetration,
)

#: Two tetrahedra sharing the face (1, 2, 3): a unit cube's corner and its mirror.
POINTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
CELLS = np.array([[0, 1, 2, 3], [4, 3, 2, 1]])


def test_a_pushed_through_node_inverts_its_element():
    bad = POINTS.copy()
    bad[0] = [0.6, 0.6, 0.6]  # through the shared face: the first tetrahedron turns inside out
    c = check_shape(CELLS, POINTS, bad)
    assert c.inverted_elements == 1
    # volumes scale with the apex's signed distance to the base: 1/6 -> -0.8/6, the other 2/6
    assert c.volume_change == pytest.approx((-0.8 + 2) / 3 - 1)
    assert check_shape(CELLS, POINTS, POINTS).inverted_elements == 0


def test_volume_change_and_plate_penetration_in_closed_form():
    squashed = POINTS * [1.0, 1.0, 0.5]  # half the height: half the volume
    plates = cc_plates([-1.0, 0.0], [-1.0, 0.4])  # upper plate at z = 0.4, covering all y
    c = check_shape(CELLS, POINTS, squashed, skin=np.arange(5), plates=plates, tolerance_mm=0.05)
    assert c.volume_change == pytest.approx(-0.5)
    assert c.nodes_beyond_plates == 2  # z = 0.5 at nodes 3 and 4
    assert c.max_plate_penetration_mm == pytest.approx(0.1)
    # A plate that reaches back only to y = 2 covers no node.
    behind = cc_plates([2.0, 0.0], [2.0, 0.4])
    assert check_shape(CELLS, POINTS, squashed, np.arange(5), behind).nodes_beyond_plates == 0


def test_plate_penetration_of_oblique_plates():
    """Shape and plates turned by 45 degrees about y (an MLO view): the same depths."""
    a = np.radians(45.0)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    squashed = POINTS * [1.0, 1.0, 0.5]
    plates = cc_plates([-1.0, 0.05], [0.5, 0.4])  # the upper plate covers y >= 0.5 only
    cc = plate_penetration(squashed, np.arange(5), plates)
    np.testing.assert_allclose(cc, [0.05, 0.05, 0.05, 0, 0.1])  # node 3: in front of the upper
    mlo = plate_penetration(squashed @ R.T, np.arange(5), rotate_plates(plates, R))
    np.testing.assert_allclose(mlo, cc, atol=1e-12)


def _shapes(final):
    return BreastShapes(
        unloaded=POINTS[None].astype(np.float32),
        compressed=final[None, None].astype(np.float32),
        plates=cc_plates([-1.0, -1.0], [-1.0, 2.0])[None, None],
        compression_ratio=np.array([[0.1]]),
        thickness=np.array([3.0]),
    )


class Mesh:
    """The fields of a `Trajectory` that the checks read: every node on the skin."""

    points, cells, source = POINTS, CELLS, "case01.vtu"

    def flagged(self, flag):
        return np.arange(5)


def test_checks_warn_or_refuse_a_deliberately_bad_prediction():
    bad = POINTS.copy()
    bad[0] = [0.6, 0.6, 0.6]
    assert set(check_shapes(Mesh(), _shapes(bad))) == {"unloaded", "compressed_3mm"}
    with pytest.warns(UserWarning, match=r"case01.vtu: compressed_3mm: 1 inverted tetrahedra"):
        record = PhysicalChecks()(Mesh(), _shapes(bad))
    assert record["shapes"]["compressed_3mm"]["inverted_elements"] == 1
    with pytest.raises(PhysicallyImpossible, match="1 inverted tetrahedra"):
        PhysicalChecks(on_violation="refuse")(Mesh(), _shapes(bad))
    assert PhysicalChecks(on_violation="refuse")(Mesh(), _shapes(POINTS))["violations"] == []
    with pytest.raises(ValueError, match=r"checks\.on_violation must be 'warn' or 'refuse'"):
        PhysicalChecks(on_violation="ignore")


def test_the_projection_makes_a_deliberately_bad_prediction_valid(monkeypatch):
    """A block breast (fat on a muscle slab: a chest wall) whose predicted shapes have noise
    of half an edge, skin pushed 1 mm through the upper plate and 10 % of the volume lost:
    after `ValidityProjection` no element is inverted, no skin node lies inside a plate, the
    volume is within 1 %, the chest wall is held as the FE holds it; the checks then find
    nothing."""
    m = skfem.MeshTet.init_tensor(*(np.linspace(0.0, 10.0, 6),) * 3)
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    muscle = p[t, 1].mean(axis=1) < 2.0  # the slab y < 2 is muscle, its top face the wall
    flags = np.where(np.isclose(p[:, 1], 2.0), NodeFlag.MUSCLE_INTERFACE, 0)
    boundary = np.isclose(p, 0).any(axis=1) | np.isclose(p, 10).any(axis=1)
    flags = (flags | np.where(boundary & (p[:, 1] > 2.0), NodeFlag.SKIN, 0)).astype(np.uint8)
    tissue = np.where(muscle, Tissue.MUSCLE, Tissue.FAT).astype(np.uint8)
    traj = Trajectory(p, t, tissue, np.full(len(p), 2, np.uint8), flags, np.zeros((0, 3), int))
    traj.metadata["source"] = "block.vtu"
    rng = np.random.default_rng(3)
    compressed = 5.0 + 0.93 * (p - 5.0) + rng.normal(0, 0.5, p.shape)  # -20 % volume ...
    compressed[p[:, 2] == 10.0, 2] += 1.0  # ... the top face into the upper plate at z = 10
    plates = cc_plates([-1.0, 0.0], [-1.0, 10.0])
    shapes = BreastShapes(
        unloaded=p[None].astype(np.float32),
        compressed=compressed[None, None].astype(np.float32),
        plates=plates[None, None],
        compression_ratio=np.array([[0.0]]),
        thickness=np.array([10.0]),
    )
    before = check_shapes(traj, shapes)["compressed_10mm"]
    assert before.inverted_elements > 0 and before.nodes_beyond_plates > 0
    assert before.volume_change < -0.05
    out, record = ValidityProjection()(traj, shapes)
    after = check_shapes(traj, out, tolerance_mm=1e-5)["compressed_10mm"]
    assert after.inverted_elements == 0 and after.nodes_beyond_plates == 0
    assert abs(after.volume_change) <= 0.01 + 1e-6
    # held as the FE holds them: the muscle where it was, the interface on the wall y = 2
    wall = np.isclose(p[:, 1], 2.0)
    held = np.setdiff1d(np.unique(t[muscle]), np.flatnonzero(wall))
    np.testing.assert_allclose(out.compressed[0, 0, held], p[held], atol=1e-5)
    np.testing.assert_allclose(out.compressed[0, 0, wall, 1], 2.0, atol=1e-5)
    assert record["steps_moved"] == 1 and 0 < record["moved_rms_mm"] < 1.0

    # a step without a valid shape stays as predicted, with a warning and a record
    def no_sweeps(cells, reference, skin=None, *args):
        c = constraints(cells, reference, skin, *args)
        return c if skin is None else replace(c, max_sweeps=0)  # the compression steps fail

    monkeypatch.setattr(validity, "constraints", no_sweeps)
    with pytest.warns(UserWarning, match=r"block.vtu: no valid shape found for 1 step\(s\)"):
        kept, record = ValidityProjection()(traj, shapes)
    np.testing.assert_array_equal(kept.compressed, shapes.compressed)
    [failed] = record["failed_steps"]
    assert failed.startswith("compression 10 mm step 1: after 0 sweeps: ")
    with pytest.raises(ValueError, match=r"projection\.min_volume_ratio must lie in"):
        ValidityProjection(min_volume_ratio=1.5)
