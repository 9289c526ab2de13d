import numpy as np
import pytest

from fem.breasts.phantom import (
    DENSITY_RANGES,
    PhantomGenerator,
    density_category,
    profile_area_factor,
)
from fem.contract.trajectory import Tissue


def test_same_seed_same_volume(generator):
    a, meta_a = generator.breast(3, "R")
    b, meta_b = PhantomGenerator(seed=7).breast(3, "R")
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.affine, b.affine)
    assert meta_a == meta_b


def test_other_seed_other_patient():
    a = PhantomGenerator(seed=1).shape(0, "L")
    b = PhantomGenerator(seed=2).shape(0, "L")
    assert a.target_volume_cm3 != b.target_volume_cm3


def test_breast_volume_matches_target(generator):
    for lat in "LR":
        shape = generator.shape(2, lat)
        _, meta = generator.breast(2, lat)
        assert meta["breast_volume_cm3"] == pytest.approx(shape.target_volume_cm3, rel=0.02)


def test_left_right_similar_not_identical(generator):
    left, right = generator.shape(4, "L"), generator.shape(4, "R")
    assert left != right
    assert 0.7 < left.target_volume_cm3 / right.target_volume_cm3 < 1.4
    (_, ml), (_, mr) = generator.breast(4, "L"), generator.breast(4, "R")
    assert ml["site"] == mr["site"] and ml["laterality"] == "L" and mr["laterality"] == "R"


def test_laterality_in_ras(phantom, generator):
    """RAS+: the right breast lies at +x, the left at -x; both in front of the muscle."""
    volume_l, _ = phantom
    volume_r, _ = generator.breast(1, "R")
    for vol, sign in ((volume_l, -1), (volume_r, 1)):
        ijk = np.argwhere(vol.labels == Tissue.FAT)
        xyz = ijk @ vol.affine[:3, :3].T + vol.affine[:3, 3]
        assert np.sign(xyz[:, 0].mean()) == sign
        muscle = np.argwhere(vol.labels == Tissue.MUSCLE) @ vol.affine[:3, :3].T + vol.affine[:3, 3]
        assert muscle[:, 1].mean() < xyz[:, 1].mean()


def test_tissues_and_glandular_fraction(phantom):
    volume, meta = phantom
    assert set(np.unique(volume.labels)) == {0, 1, 2, 3}
    assert 0.01 < meta["glandular_fraction"] < 0.36
    assert meta["density_category"] == density_category(meta["glandular_fraction"])
    assert 0.05 <= meta["target_compression_ratio"] <= 0.775
    assert meta["compressed_thickness_mm"] == pytest.approx(
        (1 - meta["target_compression_ratio"]) * meta["uncompressed_thickness_mm"]
    )


def test_density_categories():
    assert [density_category(f) for f in (0.02, 0.05, 0.1, 0.3)] == ["a", "b", "c", "d"]
    assert DENSITY_RANGES["b"][0] == DENSITY_RANGES["a"][1]


def test_profile_area_factor_closed_forms():
    # q = 2: half ellipsoid, volume 2/3 pi a b p; q = 1: cone, pi/3.
    assert profile_area_factor(2.0) == pytest.approx(2 * np.pi / 3)
    assert profile_area_factor(1.0) == pytest.approx(np.pi / 3)


def test_cohort_distributions():
    """Over 300 patients: ~10 % site A, volumes in range, compression mostly 30-60 %."""
    gen = PhantomGenerator(seed=0)
    pats = [gen.patient(i) for i in range(300)]
    site_a = np.mean([p["site"] == "A" for p in pats])
    assert 0.05 < site_a < 0.16
    vol = np.array([p["volume_cm3"] for p in pats])
    assert vol.min() >= 100 and vol.max() <= 2500
    cr = np.array([p["compression_ratio"] for p in pats])
    assert 0.05 <= cr.min() < 0.1 and 0.72 < cr.max() <= 0.775  # the tails are covered
    assert np.mean((cr >= 0.3) & (cr <= 0.6)) > 0.7
    assert np.mean(cr > 0.6) < 0.15
    cats = {p["density_category"] for p in pats}
    assert cats == {"a", "b", "c", "d"}


def test_bad_laterality(generator):
    with pytest.raises(ValueError, match="laterality"):
        generator.shape(0, "X")


def test_compression_quantile_inverts_distribution():
    from fem.breasts.phantom import COMPRESSION_RANGE, SITES, compression_quantile

    site = SITES[1]
    assert compression_quantile(site, 0.0) == pytest.approx(COMPRESSION_RANGE[0])
    assert compression_quantile(site, 1.0) == pytest.approx(COMPRESSION_RANGE[1])
    assert compression_quantile(site, 0.5) == pytest.approx(site.compression_mean, abs=0.01)
    u = np.linspace(0, 1, 101)
    assert np.all(np.diff([compression_quantile(site, x) for x in u]) > 0)
