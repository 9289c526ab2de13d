"""Closed-form checks of the decoupled neo-Hookean law."""

import numpy as np
import pytest

from fem.engine.material import (
    cauchy_stress,
    isochoric_energy,
    isochoric_pk1,
    isochoric_tangent,
    lame_parameters,
    neo_hookean_pk1,
    uniaxial_lateral_stretch,
)

MU, KAPPA = lame_parameters(1100.0, 0.495)  # fat


def uniaxial(stretch: float) -> np.ndarray:
    """F of uniaxial stress along z: the lateral stretch makes the lateral stress vanish."""
    lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
    return np.diag([lateral, lateral, stretch])


def test_lame_parameters():
    mu, kappa = lame_parameters(1100.0, 0.495)
    assert mu == pytest.approx(1100 / 2.99) and kappa == pytest.approx(1100 / 0.03)
    with pytest.raises(ValueError, match="Poisson"):
        lame_parameters(1.0, 0.5)


def test_uniaxial_compression_closed_form():
    F = uniaxial(0.5)
    assert neo_hookean_pk1(F, MU, KAPPA)[2, 2] == pytest.approx(-1284.0, rel=5e-3)
    F = uniaxial(0.24)
    assert F[0, 0] == pytest.approx(2.027, abs=1e-3)
    assert np.linalg.det(F) == pytest.approx(0.9861, abs=1e-4)
    assert cauchy_stress(F, MU, KAPPA)[2, 2] == pytest.approx(-1525.5, rel=5e-3)


def test_rigid_rotation_is_stress_free():
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    np.testing.assert_allclose(neo_hookean_pk1(R, MU, KAPPA), 0, atol=1e-9)
    assert isochoric_energy(R, MU) == pytest.approx(0, abs=1e-10)


def test_pk1_is_energy_derivative_and_tangent_is_pk1_derivative():
    rng = np.random.default_rng(1)
    F = np.eye(3) + 0.25 * rng.standard_normal((4, 3, 3))
    eps = 1e-6
    P, A = isochoric_pk1(F, MU), isochoric_tangent(F, MU)
    for k in range(3):
        for l in range(3):
            d = np.zeros((3, 3))
            d[k, l] = eps
            dW = (isochoric_energy(F + d, MU) - isochoric_energy(F - d, MU)) / (2 * eps)
            np.testing.assert_allclose(dW, P[:, k, l], rtol=1e-6, atol=1e-6)
            dP = (isochoric_pk1(F + d, MU) - isochoric_pk1(F - d, MU)) / (2 * eps)
            np.testing.assert_allclose(dP, A[:, :, :, k, l], rtol=1e-6, atol=1e-5)
