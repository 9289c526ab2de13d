"""Decoupled compressible neo-Hookean material (as ABAQUS, NiftySim and sfepy use it).

Strain energy per unit reference volume (Pa = J/m^3 = mJ/mm^3 / 1e-3 ... units: stresses in Pa
when the moduli are in Pa, whatever the length unit):

    psi(F) = mu/2 (J^(-2/3) I1 - 3) + K/2 (J - 1)^2,    I1 = F : F,  J = det F,

with the shear modulus ``mu`` and bulk modulus ``K`` from Young's modulus and Poisson's ratio
(`lame_parameters`). The isochoric part is evaluated per element; the volumetric part per node
on volume-averaged J in the element formulation (`fem.engine.assembly`), which is why the two parts
have separate functions here.

Arrays of deformation gradients have shape (..., 3, 3); results keep the leading shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fem.engine.tensor import determinant, inverse


def lame_parameters(young: NDArray | float, poisson: NDArray | float) -> tuple[NDArray, NDArray]:
    """Shear and bulk moduli of an isotropic material.

    Parameters
    ----------
    young : float or array
        Young's modulus E, Pa.
    poisson : float or array
        Poisson's ratio nu, in (-1, 0.5).

    Returns
    -------
    mu, kappa : arrays
        ``mu = E / (2 (1 + nu))`` and ``kappa = E / (3 (1 - 2 nu))``, Pa.
    """
    young, poisson = np.asarray(young, float), np.asarray(poisson, float)
    if np.any(poisson >= 0.5) or np.any(poisson <= -1.0):
        raise ValueError(f"Poisson's ratio must lie in (-1, 0.5), got {poisson}")
    return young / (2.0 * (1.0 + poisson)), young / (3.0 * (1.0 - 2.0 * poisson))


def isochoric_energy(F: NDArray, mu: NDArray | float) -> NDArray:
    """``mu/2 (J^(-2/3) I1 - 3)``, Pa, shape F.shape[:-2]."""
    J = determinant(F)
    return 0.5 * mu * (J ** (-2.0 / 3.0) * np.einsum("...ij,...ij->...", F, F) - 3.0)


def isochoric_pk1(F: NDArray, mu: NDArray | float) -> NDArray:
    """First Piola-Kirchhoff stress of the isochoric part, ``mu J^(-2/3) (F - I1/3 F^-T)``, Pa."""
    mu = np.asarray(mu, float)[..., None, None]
    Finv, J = inverse(F)
    J = J[..., None, None]
    I1 = np.einsum("...ij,...ij->...", F, F)[..., None, None]
    FinvT = np.swapaxes(Finv, -1, -2)
    return mu * J ** (-2.0 / 3.0) * (F - I1 / 3.0 * FinvT)


def isochoric_tangent(F: NDArray, mu: NDArray | float) -> NDArray:
    """``dP/dF`` of the isochoric part, Pa, shape (..., 3, 3, 3, 3) indexed [i, j, k, l].

    With ``a = J^(-2/3)``:
    ``A_ijkl = mu a [d_ik d_jl - 2/3 (F^-T_ij F_kl + F_ij F^-T_kl) + 2/9 I1 F^-T_ij F^-T_kl
    + I1/3 F^-1_li F^-1_jk]``.
    """
    mu = np.asarray(mu, float)[..., None, None, None, None]
    Finv, J = inverse(F)
    FinvT = np.swapaxes(Finv, -1, -2)
    J = J[..., None, None, None, None]
    I1 = np.einsum("...ij,...ij->...", F, F)[..., None, None, None, None]
    eye = np.eye(3)
    A = (
        np.einsum("ik,jl->ijkl", eye, eye)
        - 2.0
        / 3.0
        * (
            np.einsum("...ij,...kl->...ijkl", FinvT, F)
            + np.einsum("...ij,...kl->...ijkl", F, FinvT)
        )
        + 2.0 / 9.0 * I1 * np.einsum("...ij,...kl->...ijkl", FinvT, FinvT)
        + I1 / 3.0 * np.einsum("...li,...jk->...ijkl", Finv, Finv)
    )
    return mu * J ** (-2.0 / 3.0) * A


def volumetric_energy(J: NDArray, kappa: NDArray | float) -> NDArray:
    """``U(J) = K/2 (J - 1)^2``, Pa."""
    return 0.5 * kappa * (J - 1.0) ** 2


def volumetric_pressure(J: NDArray, kappa: NDArray | float) -> NDArray:
    """``U'(J) = K (J - 1)``: the (negative mean) Kirchhoff-like pressure conjugate to J, Pa."""
    return kappa * (J - 1.0)


def volumetric_stiffness(J: NDArray, kappa: NDArray | float) -> NDArray:
    """``U''(J) = K``, Pa, broadcast to J's shape."""
    return np.broadcast_to(np.asarray(kappa, float), np.shape(J)).copy()


def neo_hookean_pk1(F: NDArray, mu: NDArray | float, kappa: NDArray | float) -> NDArray:
    """Total first Piola-Kirchhoff stress of the decoupled model at a material point, Pa."""
    Finv, J = inverse(F)
    J, FinvT = J[..., None, None], np.swapaxes(Finv, -1, -2)
    p = volumetric_pressure(J, np.asarray(kappa, float)[..., None, None])
    return isochoric_pk1(F, mu) + p * J * FinvT


def cauchy_stress(F: NDArray, mu: NDArray | float, kappa: NDArray | float) -> NDArray:
    """Cauchy stress ``P F^T / J``, Pa."""
    J = determinant(F)[..., None, None]
    return neo_hookean_pk1(F, mu, kappa) @ np.swapaxes(F, -1, -2) / J


def uniaxial_lateral_stretch(stretch: float, mu: float, kappa: float) -> float:
    """Lateral stretch of uniaxial stress along one axis (the lateral stress vanishes).

    The closed-form reference of the verification tests: with ``a`` this value,
    ``F = diag(a, a, stretch)`` and ``neo_hookean_pk1(F)[2, 2]`` is the nominal stress.
    """
    from scipy.optimize import brentq

    def lateral_stress(a: float) -> float:
        return float(neo_hookean_pk1(np.diag([a, a, stretch]), mu, kappa)[0, 0])

    return float(brentq(lateral_stress, 0.2, 5.0))
