"""The inverse (backward-displacement) unloaded state: closed form, fixed point, failures."""

from dataclasses import replace

import numpy as np
import pytest
import skfem
from scipy.integrate import quad
from scipy.optimize import brentq

from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.boundary import chest_wall, chest_wall_fascia, chest_wall_nodes
from fem.engine.constraints import NodeFrames, equilibrium_path
from fem.engine.inverse import (
    InverseError,
    check_orientation,
    inverse_unloaded_state,
    prone_gravity,
)
from fem.engine.material import lame_parameters
from fem.engine.simulation import PAPER_MATERIALS, breast_model, unloaded_state
from fem.engine.solver import DEFAULT_NEWTON, GRAVITY_FORCE_DENSITY, nodal_body_force

FAT_ONLY = {"fat": PAPER_MATERIALS["fat"]}


def hanging_column(width: float = 20.0, length: float = 30.0, n_y: int = 13) -> Trajectory:
    """A fat column along +y (anterior) on a sliding chest wall at y = 0, without skin."""
    m = skfem.MeshTet.init_tensor(
        np.linspace(-width / 2, width / 2, 5),
        np.linspace(0, length, n_y),
        np.linspace(-width / 2, width / 2, 5),
    )
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    flags = np.where(np.isclose(p[:, 1], 0), NodeFlag.MUSCLE_INTERFACE, 0).astype(np.uint8)
    return Trajectory(
        p,
        t.astype(np.int64),
        np.full(len(t), Tissue.FAT, np.uint8),
        np.full(len(p), 2, np.uint8),
        flags,
        np.zeros((0, 3), np.int64),
        metadata={"source": "column"},
    )


def reload(traj: Trajectory, reference: np.ndarray, materials) -> np.ndarray:
    """``reference`` loaded by prone gravity, ramped from zero (independent of fem.engine.inverse),
    on the sliding chest wall with its fascia anchored on ``reference``."""
    moved = replace(traj, points=reference)
    model = breast_model(moved, materials, fascia=chest_wall_fascia(moved, reference, "sliding"))
    frames = NodeFrames.build(traj.n_nodes, chest_wall(traj, traj.points))
    f = nodal_body_force(model.body, np.array([0.0, GRAVITY_FORCE_DENSITY, 0.0]))
    record = [0.25, 0.5, 0.75, 1.0]
    return equilibrium_path(model, frames, reference, lambda s: s * f, record, DEFAULT_NEWTON)[-1]


def uniaxial_hanging_sag(length: float) -> float:
    """Sag, mm, of an incompressible neo-Hookean fat column of imaged ``length`` hanging under
    its weight: the Cauchy stress at imaged height z is rho g (L - z) = mu (l^2 - 1/l), so the
    unloaded length is int_0^L dz / l(z). (The simple reversal of this 1D problem gives the same
    length: its stretch 1/l under the nominal stress -rho g (L - Z) solves the same equation.)"""
    mu, _ = lame_parameters(PAPER_MATERIALS["fat"].young, 0.5 - 1e-9)
    stress = GRAVITY_FORCE_DENSITY / mu

    def stretch(z: float) -> float:
        return brentq(lambda s: s * s - 1 / s - stress * (length - z), 0.5, 5.0)

    return quad(lambda z: 1 - 1 / stretch(z), 0, length)[0]


def test_hanging_column_matches_uniaxial_closed_form():
    """The top face slides (held along y only, pinned against rigid motion): uniaxial."""
    traj = hanging_column()
    result = inverse_unloaded_state(traj, FAT_ONLY, n_load_steps=4, chest="anteroposterior")
    assert result.converged and result.residuals[-1] < 0.01
    tip = np.isclose(traj.points[:, 1], 30.0)
    sag = (traj.points - result.points)[tip, 1].mean()
    assert sag == pytest.approx(uniaxial_hanging_sag(30.0), rel=0.02)  # 3.38 mm, 11 % strain
    interface = traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    np.testing.assert_array_equal(result.points[interface, 1], traj.points[interface, 1])


@pytest.fixture(scope="module")
def inverse(breast_mesh):
    return inverse_unloaded_state(breast_mesh, n_load_steps=4)


def test_inverse_loaded_by_prone_gravity_reproduces_the_image(breast_mesh, inverse):
    assert inverse.converged and inverse.iterations >= 2
    assert inverse.residuals[0] > 5.0  # the imaged shape itself sags by several mm
    assert inverse.residuals[-1] < 0.01
    assert np.all(signed_volume(inverse.points, breast_mesh.cells) > 0)
    # An independent cold load ramp from the returned reference lands on the image.
    loaded = reload(breast_mesh, inverse.points, PAPER_MATERIALS)
    assert np.linalg.norm(loaded - breast_mesh.points, axis=1).max() < 0.01
    np.testing.assert_allclose(loaded, inverse.loaded, atol=1e-3)


def test_inverse_differs_from_the_simple_reversal(breast_mesh, inverse):
    simple = unloaded_state(breast_mesh, n_steps=4)[-1]
    # The simple reversal is no fixed point: loaded again it misses the image by over a mm ...
    misfit = np.linalg.norm(reload(breast_mesh, simple, PAPER_MATERIALS) - breast_mesh.points, 1)
    assert misfit.max() > 1.0
    # ... and it lies over half a mm from the inverse, while both sag posteriorly (first order).
    assert np.linalg.norm(simple - inverse.points, axis=1).max() > 0.5
    front = breast_mesh.points[:, 1] > np.percentile(breast_mesh.points[:, 1], 90)
    sag_simple = (breast_mesh.points - simple)[front, 1].mean()
    sag_inverse = (breast_mesh.points - inverse.points)[front, 1].mean()
    assert sag_inverse > 1.0 and sag_inverse == pytest.approx(sag_simple, rel=0.2)
    # The reversal sags more (its largest node sag is larger than the inverse's).
    sag = np.linalg.norm(breast_mesh.points - inverse.points, axis=1).max()
    assert np.linalg.norm(breast_mesh.points - simple, axis=1).max() > sag


def test_one_update_is_not_converged(breast_mesh, inverse):
    result = inverse_unloaded_state(breast_mesh, max_iterations=1, n_load_steps=4)
    assert not result.converged and result.iterations == 1 and len(result.residuals) == 2
    assert result.residuals[0] == pytest.approx(inverse.residuals[0])
    assert 0.01 < result.residuals[1] < result.residuals[0]


def test_plain_iteration_converges_slower_than_aitken():
    traj = hanging_column()
    plain = inverse_unloaded_state(traj, FAT_ONLY, n_load_steps=4, relaxation="none")
    aitken = inverse_unloaded_state(traj, FAT_ONLY, n_load_steps=4)
    assert plain.converged and aitken.converged
    assert plain.relaxation == [1.0] * plain.iterations
    assert aitken.iterations < plain.iterations
    np.testing.assert_allclose(plain.points, aitken.points, atol=0.02)


def test_inverted_iterate_raises():
    traj = hanging_column()
    flipped = traj.points.copy()
    flipped[:, 1] *= -1  # mirrored: every element inverted
    with pytest.raises(InverseError, match=r"column: .*X_3 inverts 1152 of 1152 elements"):
        check_orientation(traj, flipped, 3)
    check_orientation(traj, traj.points, 0)  # the imaged mesh passes


def test_input_errors():
    traj = hanging_column()
    with pytest.raises(ValueError, match="relaxation must be"):
        inverse_unloaded_state(traj, FAT_ONLY, relaxation="anderson")
    unflagged = replace(traj, node_flags=np.zeros_like(traj.node_flags))
    # without muscle, the flat posterior face (y = 0) is the chest wall, as flagged
    np.testing.assert_array_equal(
        chest_wall_nodes(unflagged), traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    )
    with_muscle = replace(unflagged, tissue=np.where(np.arange(traj.n_cells) == 0, 3, 1))
    with pytest.raises(ValueError, match="no muscle/breast interface nodes"):
        inverse_unloaded_state(with_muscle, FAT_ONLY)
    np.testing.assert_allclose(prone_gravity(), [0.0, GRAVITY_FORCE_DENSITY, 0.0])
