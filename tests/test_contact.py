"""Plate contact: the C2 ramp, derivatives, and a block squeezed between frictionless plates."""

import numpy as np
import pytest
import skfem
from conftest import assert_exact_derivatives

from fem.assembly import HyperelasticBody, Model
from fem.contact import PlateContact, nodal_areas, smooth_ramp
from fem.material import lame_parameters, neo_hookean_pk1, uniaxial_lateral_stretch
from fem.mesh import boundary_faces
from fem.quality import signed_volume
from fem.solver import load_ramp

MU, KAPPA = lame_parameters(1100.0, 0.495)


def test_smooth_ramp_is_c2():
    delta = 0.1
    s = np.array([-1.0, 0.0, 0.05, delta - 1e-12, delta + 1e-12, 1.0])
    phi, d1, d2 = smooth_ramp(s, delta)
    assert phi[0] == d1[0] == d2[0] == 0
    np.testing.assert_allclose(phi[3], phi[4], atol=1e-10)
    np.testing.assert_allclose(d1[3], d1[4], atol=1e-10)
    np.testing.assert_allclose(d2[3], d2[4], atol=1e-9)
    eps = 1e-7
    for v in (0.03, 0.5):
        p_hi, d_hi, _ = smooth_ramp(np.array([v + eps]), delta)
        p_lo, d_lo, _ = smooth_ramp(np.array([v - eps]), delta)
        _, d1v, d2v = smooth_ramp(np.array([v]), delta)
        assert (p_hi - p_lo)[0] / (2 * eps) == pytest.approx(d1v[0], rel=1e-6)
        assert (d_hi - d_lo)[0] / (2 * eps) == pytest.approx(d2v[0], rel=1e-6)


def cube(n: int = 5, size: float = 20.0):
    m = skfem.MeshTet.init_tensor(*[np.linspace(0, size, n)] * 3)
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return p, t


def test_contact_force_and_tangent_are_derivatives():
    p, t = cube()
    faces, _ = boundary_faces(p, t)
    top = np.flatnonzero(np.isclose(p[:, 2], 20))
    plate = PlateContact(top, nodal_areas(p, faces)[top], 19.9, -1, 5.0, len(p), smoothing=0.2)
    x = p + 0.1 * np.random.default_rng(4).standard_normal(p.shape)
    assert_exact_derivatives(plate, x, eps=1e-7, rtol=1e-5)
    # Nodes behind the chest-side edge (y < 5) feel nothing.
    behind = x[top, 1] < 5.0
    assert np.all(plate.internal_force(x).reshape(-1, 3)[top[behind], 2] == 0)


def test_block_between_frictionless_plates():
    """Uniaxial compression to 70 %: plate force = closed-form nominal stress x area, no node
    deeper than 0.1 mm in a plate, volume change under 3 %."""
    p, t = cube()
    body = HyperelasticBody(p, t, MU, KAPPA)
    faces, _ = boundary_faces(p, t)
    areas = nodal_areas(p, faces)
    bottom, top = np.flatnonzero(np.isclose(p[:, 2], 0)), np.flatnonzero(np.isclose(p[:, 2], 20))
    lower = PlateContact(bottom, areas[bottom], 0.0, +1, -1e9, len(p))
    upper = PlateContact(top, areas[top], 20.0, -1, -1e9, len(p))
    free = np.ones_like(
        p, bool
    )  # frictionless plates leave x, y and the spin about z free: pin them
    centre = np.flatnonzero(np.all(np.isclose(p, [10, 10, 0]), axis=1))[0]
    edge = np.flatnonzero(np.all(np.isclose(p, [20, 10, 0]), axis=1))[0]
    free[centre, :2] = False
    free[edge, 1] = False

    def move(s):
        upper.height = 20.0 * (1 - 0.7 * s)

    record = np.linspace(0.1, 1.0, 10)
    X = load_ramp(
        Model(body, (lower, upper)),
        p,
        free.ravel(),
        lambda s: np.zeros(p.size),
        record,
        configure=move,
    )
    for s, x in zip(record, X, strict=True):
        move(s)
        stretch = (x[top, 2].mean() - x[bottom, 2].mean()) / 20.0
        lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
        nominal = neo_hookean_pk1(np.diag([lateral, lateral, stretch]), MU, KAPPA)[2, 2]
        assert -upper.reaction(x) / 400.0 == pytest.approx(nominal, rel=5e-3)
        assert lower.reaction(x) == pytest.approx(upper.reaction(x), rel=1e-6)
        assert max(lower.penetration(x).max(), upper.penetration(x).max()) < 0.1
    assert signed_volume(X[-1], t).sum() == pytest.approx(8000.0, rel=0.03)
