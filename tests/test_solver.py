"""Newton and load ramps: body force against closed forms, constraints, failure reporting."""

import numpy as np
import pytest
import skfem
from scipy import sparse

from fem.contract.quality import signed_volume
from fem.engine.assembly import HyperelasticBody
from fem.engine.material import lame_parameters, neo_hookean_pk1, uniaxial_lateral_stretch
from fem.engine.solver import (
    GRAVITY_FORCE_DENSITY,
    NewtonSettings,
    ReusedFactorization,
    SolverError,
    constrained,
    load_ramp,
    newton,
    nodal_body_force,
)

MU, KAPPA = lame_parameters(1100.0, 0.495)


def column(height: float, n_z: int):
    """A 20 x 20 mm column of structured tetrahedra along z, on a roller at z = 0."""
    m = skfem.MeshTet.init_tensor(
        np.linspace(0, 20, 5), np.linspace(0, 20, 5), np.linspace(0, height, n_z)
    )
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    free = np.ones_like(p, bool)
    bottom = np.isclose(p[:, 2], 0)
    free[bottom, 2] = False
    corner = np.flatnonzero(bottom & np.isclose(p[:, 0], 0) & np.isclose(p[:, 1], 0))[0]
    side = np.flatnonzero(bottom & np.isclose(p[:, 0], 20) & np.isclose(p[:, 1], 0))[0]
    free[corner, :2] = False  # rigid-body pins: they carry no load under a vertical body force
    free[side, 1] = False
    return p, t, free.ravel()


@pytest.mark.parametrize("averaging", ["element", "nodal"])
def test_self_weight_small_load_matches_linear_closed_form(averaging):
    p, t, free = column(100.0, 21)
    body = HyperelasticBody(p, t, MU, KAPPA, averaging=averaging)
    weight = 0.01 * GRAVITY_FORCE_DENSITY
    f = nodal_body_force(body, np.array([0, 0, -weight]))
    x = load_ramp(body, p, free, lambda s: s * f, [1.0])[-1]
    top = np.isclose(p[:, 2], 100)
    assert (x - p)[top, 2].mean() == pytest.approx(-weight * 100**2 / (2 * 1100.0), rel=0.015)


def test_self_weight_finite_strain_matches_uniaxial_integral():
    """Full gravity on a 30 mm column (27 % strain at its foot): the top displacement equals
    the integral of the uniaxial stretch under the weight above, int_0^L (lambda(Z) - 1) dZ."""
    from scipy.optimize import brentq

    height = 30.0
    p, t, free = column(height, 13)
    body = HyperelasticBody(p, t, MU, KAPPA)
    f = nodal_body_force(body, np.array([0, 0, -GRAVITY_FORCE_DENSITY]))
    x = load_ramp(body, p, free, lambda s: s * f, [0.5, 1.0])[-1]

    def stretch(nominal: float) -> float:
        def axial_stress(l: float) -> float:
            a = uniaxial_lateral_stretch(l, MU, KAPPA)
            return float(neo_hookean_pk1(np.diag([a, a, l]), MU, KAPPA)[2, 2]) - nominal

        return brentq(axial_stress, 0.3, 1.05)

    z = np.linspace(0, height, 61)
    lam = np.array([stretch(-GRAVITY_FORCE_DENSITY * (height - zz)) for zz in z])
    expected = np.trapezoid(lam - 1, z)
    top = np.isclose(p[:, 2], height)
    assert (x - p)[top, 2].mean() == pytest.approx(expected, rel=0.03)
    assert signed_volume(x, t).sum() == pytest.approx(signed_volume(p, t).sum(), rel=0.01)


def test_newton_reports_failure():
    p, t, free = column(100.0, 21)
    body = HyperelasticBody(p, t, MU, KAPPA)
    f = nodal_body_force(body, np.array([0, 0, -1e3 * GRAVITY_FORCE_DENSITY]))
    with pytest.raises(SolverError, match=r"line search failed|did not converge"):
        newton(body, p, free, f, NewtonSettings(max_iterations=3))


def test_reused_factorization_follows_the_active_set():
    """A factor of one active set solves another exactly: newly held DOFs by the Schur
    complement (CG converges at once), released ones by CG on the factor's diagonal."""
    rng = np.random.default_rng(0)
    n = 60
    A = sparse.random(n, n, density=0.1, random_state=1)
    K = (A @ A.T + n * sparse.eye(n)).tocsr()  # sparse SPD
    linear = ReusedFactorization(rtol=1e-12, max_iterations=60, refactor_after=100)
    keep0 = np.ones(n, bool)
    keep0[[3, 7]] = False
    b = np.where(keep0, rng.normal(size=n), 0.0)
    np.testing.assert_allclose(constrained(K, keep0) @ linear.solve(K, b, keep0), b, atol=1e-9)
    assert linear.factorizations == 1
    for held, released in (([10, 11, 40], []), ([10, 20], [3])):
        keep = keep0.copy()
        keep[held], keep[released] = False, True
        b = np.where(keep, rng.normal(size=n), 0.0)
        d = linear.solve(K, b, keep)
        np.testing.assert_allclose(constrained(K, keep) @ d, b, atol=1e-9)
        assert not d[~keep].any() and linear.factorizations == 1
        z = linear.preconditioner(keep)(b)
        if not released:  # exact: the factor's inverse on the remaining DOFs
            np.testing.assert_allclose(z, d, atol=1e-9)


def test_load_ramp_cuts_back_the_step_that_failed(monkeypatch):
    """After easy steps the increment grows past the recorded spacing; a failure must halve
    the step that failed, not the grown increment (ten halvings of an increment of 100 never
    get below a recorded step of 1/70, and the ramp gave up on breasts that converge)."""
    accepted = [0.0]

    def fake_newton(body, x, free, f_ext, settings, linear):
        load = float(f_ext[0])
        if load > 0.5 and load - accepted[0] > 4e-3:  # hard beyond half load: small steps only
            raise SolverError("too large a step")
        accepted[0] = load
        return np.full_like(x, load), 1, np.zeros(x.size)

    class Body:  # what load_ramp asks of a body besides Newton's solve
        def min_jacobian(self, x):
            return 1.0

    monkeypatch.setattr("fem.engine.solver.newton", fake_newton)
    record = np.arange(1, 71) / 70
    path = load_ramp(Body(), np.zeros((4, 3)), np.ones(12, bool), lambda s: np.full(12, s), record)
    np.testing.assert_allclose(path[:, 0, 0], record)


def test_newton_damps_a_step_no_length_of_which_descends():
    """On ``W = sum sqrt(1 + x^2)`` from x = 30 the Newton step overshoots by a factor of about
    30^3 (the curvature is 3.7e-5): no halving down to ``min_step`` descends. The damped
    (Levenberg-Marquardt) step does, and Newton converges to the minimum x = 0."""

    class Hill:
        def min_jacobian(self, x):
            return 1.0

        def energy(self, x):
            return float(np.sqrt(1 + x.ravel() ** 2).sum())

        def internal_force(self, x):
            return (x / np.sqrt(1 + x**2)).ravel()

        def tangent(self, x):
            return sparse.diags((1 + x.ravel() ** 2) ** -1.5).tocsr()

    x0 = np.full((1, 3), 30.0)
    x, _, _ = newton(Hill(), x0, np.ones(3, bool), np.zeros(3), NewtonSettings(max_contraction=0))
    assert np.abs(x).max() < 1e-6
