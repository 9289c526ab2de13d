"""Step 1 (unloaded state) on a phantom breast, and its input errors."""

import numpy as np
import pytest

from fem.breasts.mesh import Mesher
from fem.breasts.phantom import LabelVolume
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue
from fem.engine.simulation import (
    PAPER_MATERIALS,
    Material,
    Simulation,
    chest_wall_free_dofs,
    chest_wall_nodes,
    compression,
    element_moduli,
    unloaded_state,
)


@pytest.fixture(scope="module")
def unloaded(breast_mesh):
    return unloaded_state(breast_mesh, n_steps=4)


def test_unloaded_state_physics(breast_mesh, unloaded):
    assert unloaded.shape == (4, breast_mesh.n_nodes, 3)
    u = unloaded - breast_mesh.points
    interface = breast_mesh.flagged(NodeFlag.MUSCLE_INTERFACE)
    np.testing.assert_allclose(u[:, interface, 1], 0, atol=1e-12)  # fixed anteroposteriorly
    # Removing the prone (anterior) gravity moves the breast posteriorly, more at each step.
    front = breast_mesh.points[:, 1] > np.percentile(breast_mesh.points[:, 1], 90)
    sag = -u[:, front, 1].mean(axis=1)
    assert np.all(np.diff(sag) > 0) and sag[-1] > 1.0
    # Nearly incompressible: the volume changes by less than 1 %, no element inverts.
    vol = signed_volume(unloaded[-1], breast_mesh.cells)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(
        signed_volume(breast_mesh.points, breast_mesh.cells).sum(), rel=0.01
    )


def test_nodal_averaging_is_softer_than_locking_p1(breast_mesh, unloaded):
    plain = unloaded_state(breast_mesh, n_steps=1, averaging="element")
    sag_nodal = np.linalg.norm(unloaded[-1] - breast_mesh.points, axis=1).max()
    sag_p1 = np.linalg.norm(plain[-1] - breast_mesh.points, axis=1).max()
    assert sag_nodal > 1.1 * sag_p1


def test_tissue_without_material(breast_mesh):
    materials = {k: v for k, v in PAPER_MATERIALS.items() if k != "gland"}
    if not (breast_mesh.tissue == Tissue.GLAND).any():
        pytest.skip("phantom without gland elements")
    with pytest.raises(ValueError, match=r"tissue 'gland' .* has no material parameters"):
        element_moduli(breast_mesh.tissue, materials, "b.vtu")
    mu, kappa = element_moduli(breast_mesh.tissue, {**materials, "gland": Material(2500.0)})
    np.testing.assert_allclose(kappa / mu, 2 * 1.495 / (3 * 0.01))  # K / mu at nu = 0.495


def test_mesh_without_interface_nodes(breast_mesh):
    from dataclasses import replace

    no_muscle = replace(
        breast_mesh, node_flags=breast_mesh.node_flags & ~np.uint8(NodeFlag.MUSCLE_INTERFACE)
    )
    with pytest.raises(ValueError, match=r"b\.vtu: no muscle/breast interface nodes"):
        chest_wall_free_dofs(no_muscle, "b.vtu")


def test_skin_membrane_stiffens_the_breast(breast_mesh, unloaded):
    bare = unloaded_state(
        breast_mesh, {k: v for k, v in PAPER_MATERIALS.items() if k != "skin"}, n_steps=1
    )
    with_skin = np.linalg.norm(unloaded[-1] - breast_mesh.points, axis=1).max()
    assert with_skin < np.linalg.norm(bare[-1] - breast_mesh.points, axis=1).max()


@pytest.fixture(scope="module")
def compressed(breast_mesh, unloaded):
    thickness = 0.6 * np.ptp(unloaded[-1][breast_mesh.flagged(NodeFlag.SKIN), 2])
    return compression(breast_mesh, unloaded[-1], thickness, n_steps=4), thickness


def test_compression_between_plates(breast_mesh, unloaded, compressed):
    result, thickness = compressed
    assert result.positions.shape == (4, breast_mesh.n_nodes, 3)
    assert np.all(np.diff(result.compression_ratio) > 0)
    lower, upper = result.plates[-1, :, 0, 2]  # the plates' heights (CC: origin z)
    assert upper - lower == pytest.approx(thickness)
    x = result.positions[-1]
    skin = breast_mesh.flagged(NodeFlag.SKIN)
    covered = x[skin, 1] >= result.plates[-1, 0, 0, 1]
    assert x[skin[covered], 2].min() > lower - 0.1 and x[skin[covered], 2].max() < upper + 0.1
    vol = signed_volume(x, breast_mesh.cells)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(
        signed_volume(unloaded[-1], breast_mesh.cells).sum(), rel=0.03
    )


def test_compression_thicker_than_breast(breast_mesh, unloaded):
    with pytest.raises(ValueError, match=r"compressed thickness 900\.0 mm is not smaller"):
        compression(breast_mesh, unloaded[-1], 900.0, n_steps=2)


def test_clamped_nodes_instead_of_the_chest_wall(breast_mesh, tmp_path):
    """A model without interface flags runs with a user's clamped-node file; bad indices and
    an unreadable file are refused with the file named. The plates stop in front of the
    clamped nodes."""
    from dataclasses import replace

    from fem.engine.simulation import Simulation

    wall = breast_mesh.flagged(NodeFlag.MUSCLE_INTERFACE)
    bare = replace(
        breast_mesh,
        node_flags=breast_mesh.node_flags & ~np.uint8(NodeFlag.MUSCLE_INTERFACE),
        metadata={**breast_mesh.metadata, "source": "user.vtu"},
    )
    np.savetxt(tmp_path / "wall.txt", wall, fmt="%d")
    sim = Simulation(
        unloaded_steps=2,
        compression_steps=3,
        compression_ratio=0.1,
        fixed_nodes=str(tmp_path / "wall.txt"),
    )
    out = sim(bare)
    np.testing.assert_array_equal(
        out.unloaded[:, wall], np.broadcast_to(bare.points[wall], (2, len(wall), 3))
    )
    np.testing.assert_allclose(
        out.compressed[:, wall], np.broadcast_to(out.unloaded[-1][wall], (3, len(wall), 3))
    )
    assert out.compression_ratio[-1] == pytest.approx(0.1)
    np.savetxt(tmp_path / "bad.txt", [0, 10**6], fmt="%d")
    with pytest.raises(ValueError, match=r"user\.vtu: fixed nodes must be indices in \[0, "):
        Simulation(fixed_nodes=str(tmp_path / "bad.txt"), compression_ratio=0.3)(bare)
    with pytest.raises(ValueError, match=r"missing\.txt: cannot read fixed node indices"):
        Simulation(fixed_nodes=str(tmp_path / "missing.txt"), compression_ratio=0.3)(bare)


def test_a_breast_without_muscle_hangs_on_its_posterior_cut(ellipsoid_volume):
    """A segmentation cropped at the chest wall (no muscle label): its flat posterior cut face
    is the chest wall, not skin, and both steps run with its nodes held along y."""
    labels = np.where(ellipsoid_volume.labels == Tissue.MUSCLE, 0, ellipsoid_volume.labels)
    volume = LabelVolume(labels.astype(np.uint8), ellipsoid_volume.affine, "cropped.nii")
    traj = Mesher(target_elements=1500, tolerance=500)(volume, {"source": "cropped.nii"})
    chest = chest_wall_nodes(traj)
    y = traj.points[:, 1]
    assert chest.size > 20 and np.ptp(y[chest]) < 5.0 and y[chest].min() == y.min()  # ~9 mm edges
    skin_y = traj.points[traj.skin, 1].max(1)  # no skin triangle lies on the cut
    assert skin_y.min() > y.min() + 1e-9
    result = Simulation(unloaded_steps=2, compression_steps=3, compression_ratio=0.3)(traj)
    np.testing.assert_allclose(result.unloaded[:, chest, 1], np.tile(traj.points[chest, 1], (2, 1)))
    assert result.metadata["simulation"]["compression_ratio"] == pytest.approx(0.3)
    assert result.metadata["simulation"]["min_element_volume_ratio"] > 0
