"""Physical checks of predicted shapes: inverted elements, volume change, plate penetration."""

import numpy as np
import pytest

from fem.contract.plates import cc_plates, rotate_plates
from mammo_net.predictor import BreastShapes
from mammo_net.validity import (
    PhysicalChecks,
    PhysicallyImpossible,
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
