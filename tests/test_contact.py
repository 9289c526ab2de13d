"""Plate contact: exact non-penetration, the friction potential, a squeezed block and a block
pushed along a plate with Coulomb friction."""

import numpy as np
import pytest
import skfem
from conftest import assert_exact_derivatives

from fem.contract.quality import signed_volume
from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.contact import RigidPlate, friction_mollifier
from fem.engine.material import lame_parameters, neo_hookean_pk1, uniaxial_lateral_stretch
from fem.engine.solver import load_ramp

MU, KAPPA = lame_parameters(1100.0, 0.495)


def block(size=(20.0, 20.0, 20.0), n=(5, 5, 5)):
    m = skfem.MeshTet.init_tensor(*[np.linspace(0, s, k) for s, k in zip(size, n, strict=True)])
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return p, t


def test_friction_mollifier_is_c2_and_consistent():
    r = np.array([0.0, 0.3, 1 - 1e-12, 1 + 1e-12, 4.0])
    f0, f1, df1 = friction_mollifier(r)
    assert f0[0] == f1[0] == 0 and df1[0] == 2.0
    np.testing.assert_allclose([f0[2], f1[2], df1[2]], [f0[3], f1[3], df1[3]], atol=1e-10)
    assert f1[-1] == 1.0 and df1[-1] == 0.0  # full Coulomb force once slipping
    h = 1e-7
    for v in (0.3, 0.8, 2.0):
        lo, hi = friction_mollifier(np.array([v - h])), friction_mollifier(np.array([v + h]))
        _, f1v, df1v = friction_mollifier(np.array([v]))
        assert (hi[0] - lo[0])[0] / (2 * h) == pytest.approx(f1v[0], rel=1e-6)
        assert (hi[1] - lo[1])[0] / (2 * h) == pytest.approx(df1v[0], rel=1e-5, abs=1e-7)


def test_friction_force_and_tangent_are_derivatives():
    p, _ = block()
    bottom = np.flatnonzero(np.isclose(p[:, 2], 0))
    plate = RigidPlate(bottom, 0.0, +1, -1e9, len(p), friction=0.25, slip_regularization=0.1)
    rng = np.random.default_rng(3)
    plate.normal_force = rng.uniform(10, 100, len(bottom))
    plate.anchor = p[bottom][:, :2] + rng.uniform(-0.2, 0.2, (len(bottom), 2))  # stick and slip
    assert_exact_derivatives(plate, p, eps=1e-7, rtol=1e-5)
    # The friction force of a sliding node is the Coulomb limit, opposing its slip.
    slip = p[bottom][:, :2] - plate.anchor
    sliding = np.linalg.norm(slip, axis=1) > 0.1
    f = plate.internal_force(p).reshape(-1, 3)[bottom][:, :2]
    np.testing.assert_allclose(
        np.linalg.norm(f[sliding], axis=1), 0.25 * plate.normal_force[sliding], rtol=1e-12
    )
    assert np.all(np.einsum("ij,ij->i", f, slip) > 0)  # dD/dx along the slip: force opposes it


def test_plate_bounds_only_cover_nodes_in_front_of_the_chest_edge():
    p, _ = block()
    top = np.flatnonzero(np.isclose(p[:, 2], 20))
    plate = RigidPlate(top, 19.0, -1, 5.0, len(p))
    lower, upper = np.full(p.size, -np.inf), np.full(p.size, np.inf)
    plate.apply_bounds(p, lower, upper)
    z_bound = upper.reshape(-1, 3)[top, 2]
    np.testing.assert_array_equal(z_bound == 19.0, p[top, 1] >= 5.0)
    assert np.all(np.isinf(lower))


def squeeze(p, t, friction):
    """Load factor 0..1: the upper plate moves from z = 20 down to 6 (70 % compression)."""
    body = HyperelasticBody(p, t, MU, KAPPA)
    bottom, top = np.flatnonzero(np.isclose(p[:, 2], 0)), np.flatnonzero(np.isclose(p[:, 2], 20))
    lower = RigidPlate(bottom, 0.0, +1, -1e9, len(p), friction)
    upper = RigidPlate(top, 20.0, -1, -1e9, len(p), friction)
    free = np.ones_like(p, bool)  # frictionless plates leave x, y and the spin about z free
    centre = np.flatnonzero(np.all(np.isclose(p, [10, 10, 0]), axis=1))[0]
    edge = np.flatnonzero(np.all(np.isclose(p, [20, 10, 0]), axis=1))[0]
    free[centre, :2] = False
    free[edge, 1] = False
    model = Model(body, (lower, upper))

    def move(s):
        upper.height = 20.0 * (1 - 0.7 * s)

    record = np.linspace(0.1, 1.0, 10)
    X = load_ramp(model, p, free.ravel(), lambda s: np.zeros(p.size), record, configure=move)
    return model, lower, upper, record, X, move


def test_block_between_frictionless_plates():
    """Uniaxial compression to 70 %: plate force = closed-form nominal stress x area at every
    step, no node inside a plate, volume change under 3 %."""
    p, t = block()
    model, lower, upper, record, X, move = squeeze(p, t, 0.0)
    for s, x in zip(record, X, strict=True):
        move(s)
        g = model.internal_force(x)  # no external load: the gradient is the internal force
        stretch = (upper.height - lower.height) / 20.0
        lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
        nominal = neo_hookean_pk1(np.diag([lateral, lateral, stretch]), MU, KAPPA)[2, 2]
        assert -upper.reaction(x, g) / 400.0 == pytest.approx(nominal, rel=5e-3)
        assert lower.reaction(x, g) == pytest.approx(upper.reaction(x, g), rel=1e-6)
        assert max(lower.penetration(x).max(), upper.penetration(x).max()) <= 1e-12
        # Frictionless: the plate faces stay flat and expand freely (uniform lateral stretch).
        assert np.ptp(x[upper.nodes, 2]) < 1e-9
    assert signed_volume(X[-1], t).sum() == pytest.approx(8000.0, rel=0.03)


def test_friction_holds_the_faces_of_a_squeezed_block():
    """With friction 0.25 the contact faces expand less than the free mid-plane (barrelling),
    and the squeeze needs more force than without friction."""
    p, t = block()
    model, lower, upper, record, X, move = squeeze(p, t, 0.25)
    x = X[-1]
    width = {z: np.ptp(x[np.isclose(p[:, 2], z), 0]) for z in (0.0, 10.0)}
    assert width[0.0] < 0.95 * width[10.0]
    move(record[-1])
    g = model.internal_force(x)
    stretch = 0.3
    lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
    frictionless = -neo_hookean_pk1(np.diag([lateral, lateral, stretch]), MU, KAPPA)[2, 2] * 400
    assert upper.reaction(x, g) > 1.02 * frictionless
    assert max(lower.penetration(x).max(), upper.penetration(x).max()) <= 1e-12


def test_block_pushed_along_a_plate_slips_at_the_coulomb_load():
    """A 20 x 20 x 10 mm block pressed onto a plate with friction 0.25 by a frictionless upper
    plate, then pushed sideways by its face x = 0: the push force rises while the block sticks
    and levels off at mu N once it slides."""
    p, t = block((20.0, 20.0, 10.0), (5, 5, 3))
    body = HyperelasticBody(p, t, MU, KAPPA)
    bottom, top = np.flatnonzero(np.isclose(p[:, 2], 0)), np.flatnonzero(np.isclose(p[:, 2], 10))
    lower = RigidPlate(bottom, 0.0, +1, -1e9, len(p), friction=0.25)
    upper = RigidPlate(top, 10.0, -1, -1e9, len(p), friction=0.0)
    model = Model(body, (lower, upper))
    pushed = np.flatnonzero(np.isclose(p[:, 0], 0) & ~np.isclose(p[:, 2], 0))
    free = np.ones_like(p, bool)
    free[pushed, 0] = False
    free[np.flatnonzero(np.all(np.isclose(p, [0, 10, 5]), axis=1)), 1] = False  # y: no load

    def move(s):  # 0..1: press to 9 mm; 1..2: push the face 3 mm along x
        upper.height = 10.0 - min(s, 1.0)

    def pusher(s):
        x = p.copy()
        x[:, 0] += 3.0 * max(s - 1.0, 0.0)
        return x

    record = np.concatenate([[0.5, 1.0], 1.0 + np.array([0.01, 0.02, 0.05, 0.5, 0.7, 0.85, 1.0])])
    X = load_ramp(
        model,
        p,
        free.ravel(),
        lambda s: np.zeros(p.size),
        record,
        configure=move,
        prescribed=pusher,
    )
    push, coulomb = [], []
    for s, x in zip(record[2:], X[2:], strict=True):
        move(s)
        g = model.internal_force(x)
        push.append(g.reshape(-1, 3)[pushed, 0].sum())  # reaction on the pushed face
        coulomb.append(0.25 * lower.reaction(x, g))
    push, coulomb = np.array(push), np.array(coulomb)
    assert push[0] < 0.8 * coulomb[0]  # 0.03 mm: still sticking
    np.testing.assert_allclose(push[-2:], coulomb[-2:], rtol=0.01)  # sliding at mu N
    assert np.all(push <= 1.01 * coulomb)  # never above the Coulomb load
    slide = X[-1][bottom, 0] - X[-2][bottom, 0]
    np.testing.assert_allclose(slide, 0.45, atol=0.02)  # the whole base slides with the push
    assert lower.penetration(X[-1]).max() <= 1e-12
