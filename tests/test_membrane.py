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


def test_tension_field_wrinkles_instead_of_carrying_compression():
    """The relaxed membrane: a compressed square is slack (no energy, no force); stretched by
    lam along x and squeezed across it wrinkles into uniaxial tension, W = A t mu/2 (lam^2 +
    2/lam - 3) and no stress across; its derivatives hold in every state; the plain membrane
    carries the compression."""
    p = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    mu, t, lam = 300.0, 2.0, 1.3
    skin = SkinMembrane(p, tri, mu=mu, thickness=t)
    squeezed = p * [0.8, 0.9, 1]
    assert skin.energy(squeezed) == 0 and np.abs(skin.internal_force(squeezed)).max() == 0
    plain = SkinMembrane(p, tri, mu=mu, thickness=t, tension_field=False)
    assert plain.energy(squeezed) > 0
    wrinkled = p * [lam, 0.7, 1]  # 0.7 < lam^-1/2 = 0.877: wrinkled
    assert skin.energy(wrinkled) == pytest.approx(0.5 * t * mu * (lam**2 + 2 / lam - 3))
    f = skin.internal_force(wrinkled).reshape(-1, 3)
    assert f[[1, 2], 0].sum() == pytest.approx(t * mu * (lam - lam**-2))  # uniaxial, per length
    assert f[[2, 3], 1].sum() == pytest.approx(0, abs=1e-9)  # nothing across
    _, S, _ = skin.response(np.array([np.diag([lam**2, 0.49])]))
    assert np.linalg.eigvalsh(S).min() >= 0


def test_tension_field_derivatives(breast_mesh):
    """Forces and tangent of the relaxed membrane in a mix of taut, wrinkled and slack
    triangles (a shrunk, sheared and jittered skin)."""
    skin = SkinMembrane(breast_mesh.points, breast_mesh.skin, mu=334.4)
    rng = np.random.default_rng(5)
    x = breast_mesh.points * [1.15, 0.85, 1.0] + 0.3 * rng.standard_normal(breast_mesh.points.shape)
    _, C = skin._kinematics(x)
    c = np.linalg.eigvalsh(C)
    states = {"slack": c[:, 1] <= 1, "wrinkled": (c[:, 1] > 1) & (c[:, 0] < c[:, 1] ** -0.5)}
    assert all(v.sum() > 10 for v in states.values())  # every state present
    assert_exact_derivatives(skin, x, eps=1e-7, rtol=1e-5)
