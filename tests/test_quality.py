"""Mesh geometry: the compiled signed volume against the NumPy formula and closed forms."""

import numpy as np
import pytest
import skfem

from fem.contract.quality import signed_volume


def numpy_signed_volume(points, cells):
    """The formula with NumPy gathers (the implementation before the compiled loop)."""
    q = np.moveaxis(np.asarray(points, np.float64), -1, 0)
    x0 = q[..., cells[:, 0]]
    a, b, c = (q[..., cells[:, k]] - x0 for k in (1, 2, 3))
    cross = (b[1] * c[2] - b[2] * c[1], b[2] * c[0] - b[0] * c[2], b[0] * c[1] - b[1] * c[0])
    return (a[0] * cross[0] + a[1] * cross[1] + a[2] * cross[2]) / 6.0


def test_signed_volume_equals_the_numpy_formula_to_the_last_bit():
    m = skfem.MeshTet.init_tensor(*(np.linspace(0.0, 10.0, 4),) * 3)
    p, t = m.p.T, m.t.T
    rng = np.random.default_rng(0)
    shapes = p + rng.normal(scale=2.0, size=(2, 5, *p.shape))  # (2, 5, N, 3): some inverted
    out = signed_volume(shapes, t)
    assert out.shape == (2, 5, len(t)) and out.dtype == np.float64
    np.testing.assert_array_equal(out, numpy_signed_volume(shapes, t))
    assert (out < 0).any() and (out > 0).any()
    np.testing.assert_array_equal(signed_volume(p, t.astype(np.int32)), numpy_signed_volume(p, t))
    assert abs(signed_volume(p, t)).sum() == pytest.approx(1000.0)  # the 10 mm cube
    f32 = shapes.astype(np.float32)  # computed in float64
    np.testing.assert_array_equal(signed_volume(f32, t), numpy_signed_volume(f32, t))
    assert signed_volume(p, t[:0]).shape == (0,)


def test_a_unit_tetrahedron_and_cells_past_the_nodes():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert signed_volume(p, np.array([[0, 1, 2, 3]])) == pytest.approx([1 / 6])
    assert signed_volume(p, np.array([[0, 2, 1, 3]])) == pytest.approx([-1 / 6])
    for bad in ([[0, 1, 2, 4]], [[-1, 1, 2, 3]]):
        with pytest.raises(IndexError, match="cells name nodes"):
            signed_volume(p, np.array(bad))
