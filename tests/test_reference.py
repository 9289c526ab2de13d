"""The P2 / Taylor-Hood reference solver: exact solutions, derivatives, and P1 against it."""

import numpy as np
import pytest
import skfem

from fem.contract.quality import signed_volume
from fem.engine import reference as ref
from fem.engine.assembly import HyperelasticBody
from fem.engine.material import lame_parameters, uniaxial_lateral_stretch
from fem.engine.solver import GRAVITY_FORCE_DENSITY, load_ramp, nodal_body_force

MU, KAPPA = (float(v) for v in lame_parameters(1100.0, 0.495))
FORMULATIONS = ["taylor-hood", "p2"]
TIGHT = ref.ReferenceSettings(tolerance=1e-11)


def box(lx: float, ly: float, lz: float, n: tuple[int, int, int]) -> skfem.MeshTet:
    return skfem.MeshTet.init_tensor(
        np.linspace(0, lx, n[0]), np.linspace(0, ly, n[1]), np.linspace(0, lz, n[2])
    )


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_uniaxial_compression_is_reproduced_exactly(formulation):
    """30 % compression of a cube on rollers: the homogeneous closed form F = diag(a, a, 0.7)
    lies in the discrete space, so the solution matches it to solver tolerance."""
    stretch, side = 0.7, 10.0
    disc = ref.discretize(box(side, side, side, (3, 3, 3)), MU, KAPPA, formulation)
    rollers = [ref.dofs_where(disc, lambda x, i=i: np.isclose(x[i], 0), [i]) for i in range(3)]
    top = ref.dofs_where(disc, lambda x: np.isclose(x[2], side), [2])
    fixed = np.concatenate([*rollers, top])
    prescribed = np.concatenate([np.zeros(sum(map(len, rollers))), np.full(len(top), -3.0)])
    sol = ref.solve(disc, fixed, [1.0], prescribed=prescribed, settings=TIGHT)

    a = uniaxial_lateral_stretch(stretch, MU, KAPPA)
    exact = disc.basis_s.doflocs.T * (np.array([a, a, stretch]) - 1.0)
    np.testing.assert_allclose(sol.displacement[-1], exact, atol=1e-8)
    assert ref.volume_change(disc, sol.displacement[-1]) == pytest.approx(
        (a * a * stretch - 1.0) * side**3, rel=1e-8
    )
    if formulation == "taylor-hood":
        np.testing.assert_allclose(sol.pressure[-1], KAPPA * (a * a * stretch - 1.0), rtol=1e-7)


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_column_small_self_weight_matches_linear_elasticity(formulation):
    """A 20 x 20 x 100 mm column under 1e-5 g with the exact linear-elastic displacements on its
    foot: that solution (sigma_zz = w (z - L), all other stresses zero) is quadratic, so P2
    reproduces it up to the O(strain) geometric nonlinearity, here ~1e-5; P1 could not."""
    height, young, nu = 100.0, 1100.0, 0.495
    w = 1e-5 * GRAVITY_FORCE_DENSITY

    def exact(x: np.ndarray) -> np.ndarray:  # (3, n) -> (n, 3)
        ux = -nu * w * (x[2] - height) * x[0] / young
        uy = -nu * w * (x[2] - height) * x[1] / young
        uz = w * (x[2] ** 2 / 2 - height * x[2]) / young + nu * w * (x[0] ** 2 + x[1] ** 2) / (
            2 * young
        )
        return np.stack([ux, uy, uz], axis=1)

    disc = ref.discretize(box(20.0, 20.0, height, (2, 2, 5)), MU, KAPPA, formulation)
    foot = ref.dofs_where(disc, lambda x: np.isclose(x[2], 0))
    u_exact = exact(disc.basis_s.doflocs)
    sol = ref.solve(
        disc, foot, [1.0], body_force=(0, 0, -w), prescribed=u_exact.ravel()[foot], settings=TIGHT
    )
    scale = np.abs(u_exact).max()
    np.testing.assert_allclose(sol.displacement[-1], u_exact, atol=1e-4 * scale)


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_tangent_is_the_derivative_of_the_residual(formulation):
    rng = np.random.default_rng(0)
    disc = ref.discretize(box(10.0, 10.0, 10.0, (2, 2, 3)), MU, KAPPA, formulation)
    u = 0.5 * rng.standard_normal(disc.n_u)
    p = 50.0 * rng.standard_normal(disc.n_p)
    f0 = np.zeros(disc.n_u)

    def res(z: np.ndarray) -> np.ndarray:
        state = ref.material_state(disc, z[: disc.n_u], z[disc.n_u :])
        return ref.residual(disc, state, z[disc.n_u :], f0)

    z = np.concatenate([u, p])
    K = ref.tangent_matrix(disc, ref.material_state(disc, u, p)).toarray()
    steps = np.where(np.arange(len(z)) < disc.n_u, 1e-6, 1e-4)
    fd = np.stack(
        [
            (res(z + h * e) - res(z - h * e)) / (2 * h)
            for h, e in zip(steps, np.eye(len(z)), strict=True)
        ]
    )
    np.testing.assert_allclose(K, fd.T, atol=1e-6 * np.abs(K).max())
    np.testing.assert_allclose(K, K.T, atol=1e-9 * np.abs(K).max())


def test_batched_stiffness_equals_scikit_fem_bilinear_form():
    rng = np.random.default_rng(1)
    disc = ref.discretize(box(10.0, 10.0, 10.0, (2, 2, 2)), MU, KAPPA, "p2")
    state = ref.material_state(disc, 0.5 * rng.standard_normal(disc.n_u), None)
    K_fast = ref.stiffness_uu(disc, state.tangent).toarray()
    K_skfem = ref.stiffness_form.assemble(
        disc.basis_u, A=np.moveaxis(state.tangent, (2, 3, 4, 5), (0, 1, 2, 3))
    ).toarray()
    np.testing.assert_allclose(K_fast, K_skfem, atol=1e-10 * np.abs(K_skfem).max())


def test_hemisphere_meshes_are_nested_and_positively_oriented():
    coarse, fine = ref.hemisphere(50.0, 0, half=True), ref.hemisphere(50.0, 1, half=True)
    assert fine.t.shape[1] == 8 * coarse.t.shape[1]
    points, cells = ref.oriented_cells(fine)
    assert np.all(signed_volume(points, cells) > 0)
    # the same polyhedron at every level
    assert signed_volume(points, cells).sum() == pytest.approx(
        signed_volume(*ref.oriented_cells(coarse)).sum(), rel=1e-12
    )
    assert points[:, 2].min() == 0 and points[:, 0].min() == 0
    assert points[:, 2].max() == pytest.approx(50.0)


def sagging_hemisphere_p1(level: int, averaging: str, stabilization: float, g: float) -> float:
    """Apex sag (mm) of the half hemisphere of benchmarks/convergence_p2.py under g * gravity."""
    points, cells = ref.oriented_cells(ref.hemisphere(50.0, level, half=True))
    body = HyperelasticBody(points, cells, MU, KAPPA, averaging, stabilization)
    free = np.ones_like(points, dtype=bool)
    free[np.isclose(points[:, 2], 0)] = False
    free[np.isclose(points[:, 0], 0), 0] = False
    f = nodal_body_force(body, (0.0, -g * GRAVITY_FORCE_DENSITY, 0.0))
    x = load_ramp(body, points, free.ravel(), lambda s: s * f, [1.0])[-1]
    apex = np.argmin(np.linalg.norm(points - [0, 0, 50.0], axis=1))
    return float(points[apex, 1] - x[apex, 1])


def sagging_hemisphere_reference(level: int, g: float) -> float:
    mesh = ref.hemisphere(50.0, level, half=True)
    disc = ref.discretize(mesh, MU, KAPPA, "taylor-hood")
    fixed = np.union1d(
        ref.dofs_where(disc, lambda x: np.isclose(x[2], 0)),
        ref.dofs_where(disc, lambda x: np.isclose(x[0], 0), [0]),
    )
    sol = ref.solve(disc, fixed, [1.0], body_force=(0.0, -g * GRAVITY_FORCE_DENSITY, 0.0))
    apex = np.argmin(np.linalg.norm(mesh.p.T - [0, 0, 50.0], axis=1))
    return float(-sol.displacement[-1, apex, 1])


def test_production_p1_sag_is_close_to_taylor_hood_and_plain_p1_is_stiffer():
    """Quarter gravity on the coarse benchmark meshes (docs/fem-convergence.md): Taylor-Hood on
    level 0 is within 1.5 % of its finest level (6.062 mm); production P1 (nodal, 10 %) on
    level 1 lies within 8 % of it (-5.1 %), plain P1 is stiffer than pure nodal averaging."""
    reference = sagging_hemisphere_reference(0, 0.25)
    assert reference == pytest.approx(6.062, rel=0.02)  # finest Taylor-Hood level
    production = sagging_hemisphere_p1(1, "nodal", 0.1, 0.25)
    assert production == pytest.approx(reference, rel=0.08)
    assert production < reference  # P1 converges from the stiff side
    assert sagging_hemisphere_p1(1, "element", 0.0, 0.25) < sagging_hemisphere_p1(
        1, "nodal", 0.0, 0.25
    )


@pytest.mark.slow
def test_production_p1_converges_towards_taylor_hood():
    """Level 2 (8192 tetrahedra in the half): production P1 within 4 % of Taylor-Hood level 1
    (-3.0 % in the study)."""
    reference = sagging_hemisphere_reference(1, 0.25)
    assert sagging_hemisphere_p1(2, "nodal", 0.1, 0.25) == pytest.approx(reference, rel=0.04)
