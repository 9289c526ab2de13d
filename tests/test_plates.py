"""Plate frames (fem.contract.plates) and the trajectory schema version 2 that stores them."""

import json
from dataclasses import replace

import numpy as np
import pytest
from conftest import tiny_trajectory

from fem.contract.plates import (
    cc_plates,
    check_plates,
    covered,
    penetration,
    plate_basis,
    rotate_plates,
    upgrade_v1_plates,
)
from fem.contract.trajectory import SCHEMA_VERSION, Trajectory


def rotation_about_y(degrees: float) -> np.ndarray:
    """The rotation by ``degrees`` about the anteroposterior y axis (an MLO view's tilt)."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_cc_lower_plate_frame_is_the_identity():
    lower, upper = cc_plates([-3.0, -20.0], [-3.0, 25.0])
    assert np.array_equal(plate_basis(lower), np.eye(3))  # exactly: CC features stay bit-identical
    np.testing.assert_array_equal(lower, [[0, -3, -20], [0, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(upper, [[0, -3, 25], [0, 0, -1], [0, 1, 0]])
    # The upper plate's frame is turned by 180 degrees about y: x and z flip.
    np.testing.assert_array_equal(plate_basis(upper), np.diag([-1.0, 1.0, -1.0]))


def test_a_rotated_plate():
    R = rotation_about_y(45.0)
    lower, upper = rotate_plates(cc_plates([-3.0, -20.0], [-3.0, 25.0]), R)
    basis = plate_basis(lower)
    np.testing.assert_allclose(basis, R, atol=1e-15)  # the frame turns with the plate
    np.testing.assert_allclose(basis.T @ basis, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(lower[1], [np.sqrt(0.5), 0, np.sqrt(0.5)])  # normal R e_z
    # Plate-frame coordinates of turned points are the CC coordinates.
    p = np.array([[5.0, 10.0, -18.0], [1.0, -7.0, 30.0]])
    np.testing.assert_allclose((p @ R.T) @ basis, p, atol=1e-12)
    # Coverage and depth are the CC plate's for the turned points.
    cc = cc_plates([-3.0, -20.0], [-3.0, 25.0])
    for k, plate in enumerate((lower, upper)):
        np.testing.assert_array_equal(covered(p @ R.T, plate), covered(p, cc[k]))
        np.testing.assert_allclose(penetration(p @ R.T, plate), penetration(p, cc[k]), atol=1e-12)


def test_penetration_sign_and_coverage():
    lower, upper = cc_plates([0.0, -10.0], [0.0, 10.0])
    p = np.array([[0, 5, -12], [0, 5, 0], [0, 5, 11], [0, -1, 11], [0, 0, 11]], float)
    np.testing.assert_allclose(penetration(p, lower), [2, -10, -21, -21, -21])  # inside: > 0
    np.testing.assert_allclose(penetration(p, upper), [-22, -10, 1, 1, 1])
    # behind the chest-side edge (y < 0) the plate covers nothing; the edge itself is covered
    np.testing.assert_array_equal(covered(p, upper), [True, True, True, False, True])


def test_v1_upgrade():
    v1 = np.array([[[-5.0, -30.0], [-5.0, 20.0]], [[-5.0, -30.0], [-5.0, 10.0]]])  # (2, 2, 2)
    v2 = upgrade_v1_plates(v1)
    assert v2.shape == (2, 2, 3, 3)
    np.testing.assert_array_equal(v2[:, :, 0, 1:], v1)  # origins (0, y, z)
    np.testing.assert_array_equal(v2[:, :, 0, 0], 0)
    np.testing.assert_array_equal(v2[:, 0, 1], [[0, 0, 1]] * 2)
    np.testing.assert_array_equal(v2[:, 1, 1], [[0, 0, -1]] * 2)
    np.testing.assert_array_equal(v2[:, :, 2], np.broadcast_to([0, 1, 0], (2, 2, 3)))
    check_plates(v2, 2)
    with pytest.raises(ValueError, match=r"shape \(T, 2, 2\)"):
        upgrade_v1_plates(np.zeros((2, 2, 3)))


def _write_v1(path, traj: Trajectory, plates_v1: np.ndarray) -> None:
    """A trajectory file as version 1 wrote it: plates (T2, 2, 2)."""
    arrays = {
        name: getattr(traj, name)
        for name in ("points", "cells", "tissue", "node_tissue_code", "node_flags", "skin")
    }
    np.savez_compressed(
        path,
        schema_version=np.int64(1),
        metadata=np.array(json.dumps(traj.metadata)),
        unloaded=traj.unloaded,
        compressed=traj.compressed,
        plates=plates_v1,
        compression_ratio=traj.compression_ratio,
        **arrays,
    )


def test_version_1_file_is_upgraded_on_read(tmp_path):
    tiny = tiny_trajectory()
    v1 = np.stack([tiny.plates[:, :, 0, 1], tiny.plates[:, :, 0, 2]], axis=-1)  # (T2, 2, 2)
    np.testing.assert_array_equal(v1[:, 0], [[-1.0, -2.0]] * 3)  # (y, z) of the lower edge
    _write_v1(tmp_path / "v1.npz", tiny, v1)
    back = Trajectory.load(tmp_path / "v1.npz")
    assert back.plates.shape == (3, 2, 3, 3)
    np.testing.assert_array_equal(back.plates, tiny.plates)
    np.testing.assert_array_equal(back.compressed, tiny.compressed)
    # saved again, it is version 2
    back.save(tmp_path / "v2.npz")
    with np.load(tmp_path / "v2.npz") as z:
        assert int(z["schema_version"]) == SCHEMA_VERSION == 2
        assert z["plates"].shape == (3, 2, 3, 3)
    np.testing.assert_array_equal(Trajectory.load(tmp_path / "v2.npz").plates, tiny.plates)
    # a version-1 file whose plates are not (T2, 2, 2) is refused, naming the file
    _write_v1(tmp_path / "bad1.npz", tiny, tiny.plates)
    with pytest.raises(ValueError, match=r"bad1\.npz: field 'plates' of a version-1 file"):
        Trajectory.load(tmp_path / "bad1.npz")


def test_unknown_versions_are_refused(tmp_path):
    tiny = tiny_trajectory()
    tiny.save(tmp_path / "t.npz")
    with np.load(tmp_path / "t.npz") as z:
        arrays = dict(z)
    for version in (3, 0, -1):
        arrays["schema_version"] = np.int64(version)
        np.savez_compressed(tmp_path / "future.npz", **arrays)
        with pytest.raises(
            ValueError, match=rf"future\.npz: field 'schema_version' is {version}, this code reads"
        ):
            Trajectory.load(tmp_path / "future.npz")


def test_bad_plates_are_refused_naming_the_file_and_field(tmp_path):
    tiny = tiny_trajectory()
    for broken, message in [
        (lambda p: p[:, :, :2], r"must have shape \(3, 2, 3, 3\)"),
        (lambda p: p * np.array([1, 2, 1.0])[:, None], "normals that are not unit vectors"),
        (lambda p: p * np.array([1, 1, 1.01])[:, None], "axes that are not unit vectors"),
        (lambda p: np.concatenate([p[:, :, :2], p[:, :, 1:2]], axis=2), "not orthogonal"),
        (lambda p: p * np.nan, "NaN or infinite"),
    ]:
        tiny.save(tmp_path / "t.npz")
        with np.load(tmp_path / "t.npz") as z:
            arrays = dict(z)
        arrays["plates"] = broken(arrays["plates"])
        np.savez_compressed(tmp_path / "case07.npz", **arrays)
        with pytest.raises(ValueError, match=rf"case07\.npz: field 'plates' .*{message}"):
            Trajectory.load(tmp_path / "case07.npz")
    with pytest.raises(ValueError, match="field 'plates' is required"):
        Trajectory(
            tiny.points, tiny.cells, tiny.tissue, tiny.node_tissue_code, tiny.node_flags,
            tiny.skin, compressed=tiny.compressed, compression_ratio=tiny.compression_ratio,
        )  # fmt: skip
    bare = Trajectory(
        tiny.points, tiny.cells, tiny.tissue, tiny.node_tissue_code, tiny.node_flags, tiny.skin
    )
    assert bare.plates.shape == (0, 2, 3, 3)


def test_reference_shape():
    tiny = tiny_trajectory()
    np.testing.assert_array_equal(tiny.reference_shape, tiny.unloaded[-1])
    skipped = replace(tiny, unloaded=np.zeros((0, tiny.n_nodes, 3)))
    np.testing.assert_array_equal(skipped.reference_shape, tiny.points)
