"""Paper features (section 2.2) and the per-breast z-score (equation 1) on a two-element mesh."""

import numpy as np
import pytest
from conftest import tiny_trajectory

from datamodules.features import (
    COMPRESSION_FEATURES,
    UNLOADED_FEATURES,
    Normalization,
    compression_features,
    unloaded_features,
)
from fem.contract.trajectory import NodeFlag, Trajectory


@pytest.fixture
def tiny() -> Trajectory:
    return tiny_trajectory()


def test_normalization_round_trip():
    rng = np.random.default_rng(0)
    points = rng.normal([10, -50, 30], [20, 30, 25], (500, 3))
    norm = Normalization.of(points)
    z = norm.apply(points)
    np.testing.assert_allclose(z.mean(axis=0), 0, atol=1e-12)
    assert np.sqrt((z**2).sum(axis=1).mean()) == pytest.approx(1.0)  # unit RMS distance
    np.testing.assert_allclose(norm.invert(z), points, atol=1e-12)
    np.testing.assert_allclose(
        norm.invert(norm.apply(points[:, 1:], [1, 2]), [1, 2]), points[:, 1:]
    )


def test_unloaded_features_by_hand(tiny):
    features, targets, norm = unloaded_features(tiny)
    assert features.shape == (2, 5, len(UNLOADED_FEATURES)) == (2, 5, 11)
    mean = tiny.points.mean(axis=0)  # (0.2, 0.2, -0.2)
    scale = np.sqrt(((tiny.points - mean) ** 2).sum(axis=1).mean())
    np.testing.assert_allclose(norm.mean, [0.2, 0.2, -0.2])
    np.testing.assert_allclose(features[1, 4, :3], ([0, 0, -2] - mean) / scale, rtol=1e-6)
    np.testing.assert_array_equal(features[:, 0, 3], [1, 2])  # step number
    # Volumes 1/6 (fat) and 1/3 (muscle): fractions 1/3, 0, 2/3; volume 0.5 mm^3; 1/2 of elements.
    np.testing.assert_allclose(features[0, 2, 4:11], [1 / 3, 0, 2 / 3, 0.5, 0.5, 0, 0.5], rtol=1e-6)
    np.testing.assert_allclose(norm.invert(targets), tiny.unloaded, atol=1e-5)


def test_compression_features_by_hand(tiny):
    features, targets, norm = compression_features(tiny)
    assert features.shape == (3, 5, len(COMPRESSION_FEATURES)) == (3, 5, 22)
    rest = tiny.unloaded[-1]
    np.testing.assert_allclose(norm.mean, rest.mean(axis=0))
    np.testing.assert_allclose(features[0, :, :3], norm.apply(rest), rtol=1e-6, atol=1e-6)
    i = COMPRESSION_FEATURES.index
    np.testing.assert_allclose(
        features[:, 0, i("upper_plate_displacement")],
        np.array([0.3, 0.6, 0.9]) / norm.scale,
        rtol=1e-6,
    )
    np.testing.assert_allclose(
        features[2, 3, i("lower_plate_edge_y")], (-1 - norm.mean[1]) / norm.scale, rtol=1e-6
    )
    np.testing.assert_allclose(
        features[2, 3, i("upper_plate_edge_z")], (0.1 - norm.mean[2]) / norm.scale, rtol=1e-5
    )
    np.testing.assert_array_equal(features[0, :, i("upper_contact")], [0, 0, 0, 1, 0])
    np.testing.assert_array_equal(features[0, :, i("skin")], [1, 0, 0, 1, 0])
    # Table 2 bits (gland, fat, muscle): code 3 = fat/muscle interface, 2 fat, 1 muscle.
    bits = features[0, :, i("tissue_bit_2_gland") : i("tissue_bit_0_muscle") + 1]
    np.testing.assert_array_equal(bits, [[0, 1, 1]] * 3 + [[0, 1, 0], [0, 0, 1]])
    assert np.all(features[..., i("laterality")] == 1.0)  # right breast
    np.testing.assert_allclose(norm.invert(targets), tiny.compressed, atol=1e-5)


def test_compression_features_errors(tiny):
    from dataclasses import replace

    with pytest.raises(ValueError, match=r"b\.npz: metadata field 'laterality'"):
        compression_features(replace(tiny, metadata={"source": "b.npz"}))
    bare = Trajectory(
        tiny.points,
        tiny.cells,
        tiny.tissue,
        tiny.node_tissue_code,
        tiny.node_flags,
        tiny.skin,
        metadata={"source": "c.npz", "laterality": "L"},
    )
    with pytest.raises(ValueError, match=r"c\.npz: not simulated"):
        compression_features(bare)
    assert NodeFlag.UPPER_CONTACT == 4
