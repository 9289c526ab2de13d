"""Compression features in the lower plate's frame: bit-identical for cranio-caudal (CC)
plates, invariant when the whole geometry and its plates are turned into an oblique (MLO)
view, and targets that map back to the patient frame."""

import json
from dataclasses import replace

import numpy as np
import pytest
from conftest import tiny_trajectory
from test_plates import rotation_about_y

from datamodules.features import (
    CC_UPPER_NORMAL,
    COMPRESSION_FEATURES,
    Normalization,
    compression_features,
    compression_inputs,
    facing_plate,
    tissue_descriptors,
    upper_contact,
)
from datamodules.trajectories import Breast, cache_breast
from fem.contract.plates import cc_plates, rotate_plates
from fem.contract.trajectory import NodeFlag, Trajectory


def synthetic_compression(mesh: Trajectory, n_steps: int = 4) -> Trajectory:
    """``mesh`` with a made-up unloaded shape and a CC compression squeezing it towards the
    lower plate, plates where the FE would put them."""
    rest = mesh.points + np.array([0.3, -2.0, 0.1])
    skin_z = rest[mesh.flagged(NodeFlag.SKIN), 2]
    bottom, top = skin_z.min(), skin_z.max()
    ratio = 0.1 * np.arange(1, n_steps + 1)
    compressed = np.stack([rest * [1, 1, 0] + [0, 0, 1] * (bottom + (rest[:, 2:] - bottom) * (1 - r))
                           for r in ratio])  # fmt: skip
    edge = rest[:, 1].min()
    upper = bottom + (top - bottom) * (1 - ratio)
    plates = cc_plates([edge, bottom], np.stack([np.full(n_steps, edge), upper], 1))
    return replace(
        mesh,
        unloaded=rest[None],
        compressed=compressed,
        plates=plates,
        compression_ratio=ratio,
        metadata={**mesh.metadata, "laterality": "L", "source": "synthetic.npz"},
    )


@pytest.fixture(scope="module")
def cc(breast_mesh) -> Trajectory:
    return synthetic_compression(breast_mesh)


def turned(traj: Trajectory, R: np.ndarray) -> Trajectory:
    """The whole breast and its plates turned by ``R`` about the origin (an MLO view)."""
    return replace(
        traj,
        points=traj.points @ R.T,
        unloaded=traj.unloaded @ R.T,
        compressed=traj.compressed @ R.T,
        plates=rotate_plates(traj.plates, R),
    )


def legacy_compression_features(traj: Trajectory):
    """Schema version 1's features and targets, as they were computed before plate frames:
    plates as (y, z) of the CC plates' chest-side edges, everything in the patient frame."""
    plates = traj.plates[:, :, 0, 1:]  # (T, 2, 2)
    unloaded = traj.unloaded[-1]
    mean = unloaded.mean(axis=0)
    scale = float(np.sqrt(((unloaded - mean) ** 2).sum(axis=1).mean()))
    n_steps, n = len(plates), traj.n_nodes
    base = np.empty((n_steps, n, 11), np.float32)
    base[:, :, 0:3] = (unloaded - mean) / scale
    base[:, :, 3] = np.arange(1, n_steps + 1)[:, None]
    base[:, :, 4:11] = tissue_descriptors(traj)
    lower, upper = plates[:, 0, 1], plates[:, 1, 1]
    first_contact = lower + (upper - lower) / (1.0 - traj.compression_ratio)
    code = traj.node_tissue_code
    per_step = np.stack(
        [
            (first_contact - upper) / scale,
            *((plates[:, 0] - mean[[1, 2]]) / scale).T,
            *((plates[:, 1] - mean[[1, 2]]) / scale).T,
        ],
        axis=1,
    )
    per_node = np.stack(
        [
            (traj.node_flags & NodeFlag.UPPER_CONTACT) > 0,
            (traj.node_flags & NodeFlag.SKIN) > 0,
            (code >> 2) & 1,
            (code >> 1) & 1,
            code & 1,
            np.full(n, 1.0 if traj.metadata["laterality"] == "R" else 0.0),
        ],
        axis=1,
    ).astype(np.float32)
    features = np.concatenate(
        [
            base,
            np.broadcast_to(per_step[:, None, :], (n_steps, n, 5)),
            np.broadcast_to(per_node[None], (n_steps, n, 6)),
        ],
        axis=2,
    ).astype(np.float32)
    return features, ((traj.compressed - mean) / scale).astype(np.float32)


@pytest.mark.parametrize("which", ["tiny", "phantom"])
def test_cc_features_are_bit_identical_to_version_1(which, cc):
    traj = tiny_trajectory() if which == "tiny" else cc
    features, targets, norm = compression_features(traj)
    assert norm.rotation is None  # the identity is not even multiplied
    old_features, old_targets = legacy_compression_features(traj)
    assert np.array_equal(features, old_features)
    assert np.array_equal(targets, old_targets)


def test_cc_upper_contact_rule_is_the_stored_flag(breast_mesh):
    """`facing_plate` against the upper CC plate gives `annotate`'s stored flag bit for bit."""
    stored = (breast_mesh.node_flags & NodeFlag.UPPER_CONTACT) > 0
    assert stored.any() and not stored.all()
    np.testing.assert_array_equal(facing_plate(breast_mesh, CC_UPPER_NORMAL), stored)
    # ... and the lower plate's normal gives the lower-contact flag
    lower = (breast_mesh.node_flags & NodeFlag.LOWER_CONTACT) > 0
    np.testing.assert_array_equal(facing_plate(breast_mesh, [0.0, 0.0, 1.0]), lower)


@pytest.mark.parametrize("degrees", [45.0, -45.0, 30.0])
def test_mlo_features_equal_the_cc_features(cc, degrees):
    R = rotation_about_y(degrees)
    mlo = turned(cc, R)
    f_cc, t_cc, _ = compression_features(cc)
    f_mlo, t_mlo, n_mlo = compression_features(mlo)
    np.testing.assert_allclose(n_mlo.rotation, R, atol=1e-15)
    # upper contact evaluated against the oblique plate: the CC flag, node for node
    upper = COMPRESSION_FEATURES.index("upper_contact")
    np.testing.assert_array_equal(f_mlo[..., upper], f_cc[..., upper])
    np.testing.assert_array_equal(upper_contact(mlo, mlo.plates), upper_contact(cc, cc.plates))
    np.testing.assert_allclose(f_mlo, f_cc, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(t_mlo, t_cc, atol=1e-5)
    # the targets map back to the oblique breast's patient-frame positions
    np.testing.assert_allclose(n_mlo.invert(t_mlo), mlo.compressed, atol=1e-3)
    np.testing.assert_allclose(
        n_mlo.invert(n_mlo.apply(mlo.compressed)), mlo.compressed, rtol=0, atol=1e-9
    )


def test_an_mlo_view_of_the_same_breast(cc):
    """Only the plates (and the compressed shape) turned, the breast as imaged: the features
    are those of the breast turned the other way between CC plates; which nodes face the
    upper plate is no longer the stored CC flag."""
    R = rotation_about_y(45.0)
    mlo = replace(cc, plates=rotate_plates(cc.plates, R), compressed=cc.compressed @ R.T)
    features, _, _ = compression_features(mlo)
    back = turned(cc, R.T)  # the breast turned into the plates' frame, between CC plates
    back = replace(back, plates=cc.plates, compressed=cc.compressed)
    expected, _, _ = compression_features(back)
    upper = COMPRESSION_FEATURES.index("upper_contact")
    facing = facing_plate(back, CC_UPPER_NORMAL)  # the CC rule on the turned breast
    np.testing.assert_array_equal(features[0, :, upper], facing)
    assert (facing != (cc.node_flags & NodeFlag.UPPER_CONTACT > 0)).any()
    expected[..., upper] = facing
    np.testing.assert_allclose(features, expected, rtol=1e-5, atol=1e-5)


def test_skipped_unloaded_step_starts_from_the_imaged_shape(cc):
    skipped = replace(cc, unloaded=np.zeros((0, cc.n_nodes, 3)))
    features, _, norm = compression_features(skipped)
    expected, _ = compression_inputs(cc, cc.points, cc.plates, cc.compression_ratio)
    np.testing.assert_array_equal(features, expected)
    np.testing.assert_allclose(norm.mean, cc.points.mean(axis=0))


def test_normalization_files_with_and_without_rotation(tmp_path, cc):
    R = rotation_about_y(45.0)
    norm = Normalization.of(cc.points, R)
    back = Normalization.from_json(json.loads(json.dumps(norm.to_json())))
    np.testing.assert_array_equal(back.rotation, norm.rotation)
    np.testing.assert_array_equal(back.mean, norm.mean)
    assert Normalization.of(cc.points, np.eye(3)).to_json().keys() == {"mean", "scale"}
    old = Normalization.from_json({"mean": [1.0, 2.0, 3.0], "scale": 2.0})  # before rotations
    assert old.rotation is None
    np.testing.assert_array_equal(old.invert(np.zeros(3)), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="whole"):
        norm.apply(cc.points[:, 1:], [1, 2])
    # the feature cache keeps the rotation, and maps the targets back to the patient frame
    mlo = turned(cc, R)
    mlo.save(tmp_path / "P0001_L.npz")
    cache_breast(tmp_path / "P0001_L.npz", tmp_path / "P0001_L", "compression")
    breast = Breast("P0001_L", 1, "B", tmp_path / "P0001_L")
    np.testing.assert_allclose(breast.normalization().rotation, R, atol=1e-15)
    mm = breast.normalization().invert(np.asarray(breast.targets()))  # (N, T, 3)
    np.testing.assert_allclose(mm.transpose(1, 0, 2), mlo.compressed, atol=1e-3)
