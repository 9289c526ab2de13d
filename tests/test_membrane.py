"""The skin membrane: derivatives, stress-free rigid motion, closed-form equibiaxial stretch."""

import numpy as np
import pytest
from conftest import assert_exact_derivatives

from fem.engine.membrane import SkinMembrane


def test_force_and_tangent_are_derivatives(breast_mesh):
    skin = SkinMembrane(breast_mesh.points, breast_mesh.skin, mu=1000 / 2.99)
    x = breast_mesh.points + 0.5 * np.random.default_rng(3).standard_normal(
        breast_mesh.points.shape
    )
    assert_exact_derivatives(skin, x)


def test_rigid_motion_is_stress_free(breast_mesh):
    skin = SkinMembrane(breast_mesh.points, breast_mesh.skin, mu=334.4)
    a = 0.6
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    x = breast_mesh.points @ R.T + 5.0
    assert skin.energy(x) == pytest.approx(0, abs=1e-8)
    assert np.abs(skin.internal_force(x)).max() < 1e-9


def test_equibiaxial_stretch_closed_form():
    """A unit square of two triangles stretched by lam in-plane: W = A t mu/2 (2 lam^2 + lam^-4 - 3)
    and the membrane force per unit reference length is t mu (lam - lam^-5)."""
    p = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    mu, t, lam = 300.0, 2.0, 1.3
    skin = SkinMembrane(p, tri, mu=mu, thickness=t)
    x = p * [lam, lam, 1]
    assert skin.energy(x) == pytest.approx(0.5 * t * mu * (2 * lam**2 + lam**-4 - 3))
    f = skin.internal_force(x).reshape(-1, 3)
    edge = f[[1, 2], 0].sum()  # force on the x = 1 edge
    assert edge == pytest.approx(t * mu * (lam - lam**-5))
