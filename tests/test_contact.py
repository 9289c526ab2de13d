"""Plate contact: exact non-penetration, the friction potential, a squeezed block (between
cranio-caudal and between oblique plates) and a block pushed along a plate with Coulomb
friction."""

import numpy as np
import pytest
import skfem
from conftest import assert_exact_derivatives

from fem.contract.quality import signed_volume
from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.constraints import FramedModel, HeldDirections, NodeFrames, equilibrium_path
from fem.engine.contact import RigidPlate, friction_mollifier
from fem.engine.material import lame_parameters, neo_hookean_pk1, uniaxial_lateral_stretch
from fem.engine.solver import DEFAULT_NEWTON

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


def turn(angle_deg):
    """Rotation (3, 3) about y by ``angle_deg`` (the MLO plates' turn)."""
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def plate(nodes, height, side, n, friction=0.0, edge=-1e9, R=None):
    """A plate of the block's frame turned by ``R``: surface ``z = height`` (side +1: body
    above), covering ``y >= edge``."""
    R = np.eye(3) if R is None else R
    normal = R @ np.array([0.0, 0.0, side])
    return RigidPlate(nodes, R @ np.array([0.0, edge, height]), normal, R[:, 1], n, friction)


def reaction(framed, k, x, g):
    """Total normal force of plate ``k`` on the body at ``x`` with ``g = dPi/dx``, Pa mm^2."""
    frames = framed.frames
    return float(framed.contact_forces(frames.to_local(x), frames.to_local(g))[k].sum())


def test_friction_force_and_tangent_are_derivatives():
    p, _ = block()
    bottom = np.flatnonzero(np.isclose(p[:, 2], 0))
    plate_ = plate(bottom, 0.0, +1, len(p), friction=0.25, R=turn(30.0))
    rng = np.random.default_rng(3)
    plate_.normal_force = rng.uniform(10, 100, len(bottom))
    anchor = p[bottom] + rng.uniform(-0.2, 0.2, (len(bottom), 3))  # stick and slip
    plate_.anchor = anchor @ plate_.tangents.T
    assert_exact_derivatives(plate_, p, eps=1e-7, rtol=1e-5)
    # The friction force of a sliding node is the Coulomb limit, opposing its slip.
    slip = p[bottom] @ plate_.tangents.T - plate_.anchor
    sliding = np.linalg.norm(slip, axis=1) > 0.1
    f = plate_.internal_force(p).reshape(-1, 3)[bottom]
    assert np.abs(f @ plate_.normal).max() < 1e-12  # in the plate plane
    f = f @ plate_.tangents.T
    np.testing.assert_allclose(
        np.linalg.norm(f[sliding], axis=1), 0.25 * plate_.normal_force[sliding], rtol=1e-12
    )
    assert np.all(np.einsum("ij,ij->i", f, slip) > 0)  # dD/dx along the slip: force opposes it


def test_plate_bounds_only_cover_nodes_in_front_of_the_chest_edge():
    p, t = block()
    top = np.flatnonzero(np.isclose(p[:, 2], 20))
    upper = plate(top, 19.0, -1, len(p), edge=5.0)
    framed = FramedModel(
        Model(HyperelasticBody(p, t, MU, KAPPA), (upper,)),
        NodeFrames.build(len(p), HeldDirections.none(), upper.normal, top),
    )
    lower, upper_bound = framed.bounds(p)
    z_bound = upper_bound.reshape(-1, 3)[top, 2]
    np.testing.assert_array_equal(z_bound == 19.0, p[top, 1] >= 5.0)
    assert np.all(np.isinf(lower))


def squeeze(friction, angle=0.0):
    """Load factor 0..1: the upper plate moves from z = 20 down to 6 (70 % compression), in the
    block's frame turned about y by ``angle`` degrees."""
    p, t = block()
    R = turn(angle)
    x0 = p @ R.T
    body = HyperelasticBody(x0, t, MU, KAPPA)
    bottom, top = np.flatnonzero(np.isclose(p[:, 2], 0)), np.flatnonzero(np.isclose(p[:, 2], 20))
    lower = plate(bottom, 0.0, +1, len(p), friction, R=R)
    upper = plate(top, 20.0, -1, len(p), friction, R=R)
    # Frictionless plates leave the block's x, y and the spin about its z free: hold them
    # along the block's (turned) axes at two nodes of the lower face.
    centre = np.flatnonzero(np.all(np.isclose(p, [10, 10, 0]), axis=1))[0]
    edge = np.flatnonzero(np.all(np.isclose(p, [20, 10, 0]), axis=1))[0]
    held = HeldDirections(np.array([centre, centre, edge]), R[:, [0, 1, 1]].T)
    model = Model(body, (lower, upper))
    frames = NodeFrames.build(len(p), held, lower.normal, np.concatenate([bottom, top]))
    start = upper.origin.copy()

    def move(s):
        upper.origin = start + 14.0 * s * upper.normal  # the normal points down, into the block

    record = np.linspace(0.1, 1.0, 10)
    X = equilibrium_path(
        model, frames, x0, lambda s: np.zeros(p.size), record, DEFAULT_NEWTON, configure=move
    )
    return FramedModel(model, frames), lower, upper, record, X, move, t


@pytest.mark.parametrize("angle", [0.0, 45.0])
def test_block_between_frictionless_plates(angle):
    """Uniaxial compression to 70 % between cranio-caudal and between oblique (MLO, 45 deg)
    plates: plate force = closed-form nominal stress x area at every step, no node inside a
    plate along its normal, volume change under 3 %."""
    framed, lower, upper, record, X, move, t = squeeze(0.0, angle)
    model = framed.model
    for s, x in zip(record, X, strict=True):
        move(s)
        g = model.internal_force(x)  # no external load: the gradient is the internal force
        stretch = (upper.origin - lower.origin) @ lower.normal / 20.0
        lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
        nominal = neo_hookean_pk1(np.diag([lateral, lateral, stretch]), MU, KAPPA)[2, 2]
        assert -reaction(framed, 1, x, g) / 400.0 == pytest.approx(nominal, rel=5e-3)
        assert reaction(framed, 0, x, g) == pytest.approx(reaction(framed, 1, x, g), rel=1e-6)
        assert min(lower.gap(x).min(), upper.gap(x).min()) >= -1e-12
        # Frictionless: the plate faces stay flat and expand freely (uniform lateral stretch).
        assert np.ptp(x[upper.nodes] @ upper.normal) < 1e-9
    assert signed_volume(X[-1], t).sum() == pytest.approx(8000.0, rel=0.03)


def test_friction_holds_the_faces_of_a_squeezed_block():
    """With friction 0.25 the contact faces expand less than the free mid-plane (barrelling),
    and the squeeze needs more force than without friction."""
    framed, lower, upper, record, X, move, _ = squeeze(0.25)
    p, x = framed.body.points, X[-1]
    width = {z: np.ptp(x[np.isclose(p[:, 2], z), 0]) for z in (0.0, 10.0)}
    assert width[0.0] < 0.95 * width[10.0]
    move(record[-1])
    g = framed.model.internal_force(x)
    stretch = 0.3
    lateral = uniaxial_lateral_stretch(stretch, MU, KAPPA)
    frictionless = -neo_hookean_pk1(np.diag([lateral, lateral, stretch]), MU, KAPPA)[2, 2] * 400
    assert reaction(framed, 1, x, g) > 1.02 * frictionless
    assert min(lower.gap(x).min(), upper.gap(x).min()) >= -1e-12


def test_block_pushed_along_a_plate_slips_at_the_coulomb_load():
    """A 20 x 20 x 10 mm block pressed onto a plate with friction 0.25 by a frictionless upper
    plate, then pushed sideways by its face x = 0: the push force rises while the block sticks
    and levels off at mu N once it slides."""
    p, t = block((20.0, 20.0, 10.0), (5, 5, 3))
    body = HyperelasticBody(p, t, MU, KAPPA)
    bottom, top = np.flatnonzero(np.isclose(p[:, 2], 0)), np.flatnonzero(np.isclose(p[:, 2], 10))
    lower = plate(bottom, 0.0, +1, len(p), friction=0.25)
    upper = plate(top, 10.0, -1, len(p), friction=0.0)
    model = Model(body, (lower, upper))
    pushed = np.flatnonzero(np.isclose(p[:, 0], 0) & ~np.isclose(p[:, 2], 0))
    held = HeldDirections.axes(pushed, (0,)) + HeldDirections.axes(
        np.flatnonzero(np.all(np.isclose(p, [0, 10, 5]), axis=1)),
        (1,),  # y: no load
    )
    frames = NodeFrames.build(len(p), held, lower.normal, np.concatenate([bottom, top]))
    framed = FramedModel(model, frames)

    def move(s):  # 0..1: press to 9 mm; 1..2: push the face 3 mm along x
        upper.origin = np.array([0.0, -1e9, 10.0 - min(s, 1.0)])

    def pusher(s):
        x = p.copy()
        x[:, 0] += 3.0 * max(s - 1.0, 0.0)
        return x

    record = np.concatenate([[0.5, 1.0], 1.0 + np.array([0.01, 0.02, 0.05, 0.5, 0.7, 0.85, 1.0])])
    X = equilibrium_path(
        model,
        frames,
        p,
        lambda s: np.zeros(p.size),
        record,
        DEFAULT_NEWTON,
        configure=move,
        prescribed=pusher,
    )
    push, coulomb = [], []
    for s, x in zip(record[2:], X[2:], strict=True):
        move(s)
        g = model.internal_force(x)
        push.append(g.reshape(-1, 3)[pushed, 0].sum())  # reaction on the pushed face
        coulomb.append(0.25 * reaction(framed, 0, x, g))
    push, coulomb = np.array(push), np.array(coulomb)
    assert push[0] < 0.8 * coulomb[0]  # 0.03 mm: still sticking
    # Sliding at mu N: every node's friction is mu lambda along its slip; the base's lateral
    # creep tilts some slips by up to ~8 degrees from x, so the push is 1.1 % below mu N.
    np.testing.assert_allclose(push[-2:], coulomb[-2:], rtol=0.015)
    assert np.all(push <= 1.01 * coulomb)  # never above the Coulomb load
    slide = X[-1][bottom, 0] - X[-2][bottom, 0]
    np.testing.assert_allclose(slide, 0.45, atol=0.03)  # the whole base slides with the push
    assert lower.gap(X[-1]).min() >= -1e-12
