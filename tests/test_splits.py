"""Patient-level splits: no patient on both sides, site balance, fold sizes, determinism."""

import numpy as np
import pytest

from datamodules.splits import check_bounds, k_folds, one_fold_split, within_bounds


@pytest.fixture
def cohort():
    patients = np.arange(258)
    sites = np.where(np.arange(258) % 11 == 0, "A", "B")  # 24 A, 234 B
    return patients, sites


def test_one_fold_split_balanced_between_sites(cohort):
    patients, sites = cohort
    train, val = one_fold_split(patients, sites, 0.1, seed=3)
    assert len(val) == 26 and len(train) == 232
    assert not set(train) & set(val) and set(train) | set(val) == set(patients)
    site_of = dict(zip(patients, sites, strict=True))
    assert [site_of[p] for p in val].count("A") == 13  # half of the validation from each site
    again, _ = one_fold_split(patients, sites, 0.1, seed=3)
    np.testing.assert_array_equal(train, again)


def test_one_fold_split_keeps_a_training_patient_per_site():
    train, val = one_fold_split([0, 1, 2, 3, 4, 5, 6, 7, 8, 9], ["A"] + ["B"] * 9, 0.5)
    assert 0 in train and len(val) == 5


def test_k_folds_partition_patients(cohort):
    patients, sites = cohort
    fold = k_folds(patients, sites, 10, seed=1)
    sizes = np.bincount(fold, minlength=10)
    assert sizes.max() - sizes.min() <= 1 and sizes.sum() == 258
    for k in range(10):  # each site spread evenly over the folds
        a = np.sum((fold == k) & (sites == "A"))
        assert 2 <= a <= 3
    with pytest.raises(ValueError, match="n_folds must lie in"):
        k_folds(patients, sites, 1)
    with pytest.raises(ValueError, match="one entry per patient"):
        k_folds([1, 1, 2], ["A", "A", "B"], 2)


def test_conditions_within_bounds():
    cc = {"young_fat": 700.0, "young_gland": 2500.0, "friction": 0.25, "view": "cc", "angle": 45.0}
    mlo = {**cc, "view": "mlo", "angle": 58.0}
    bounds = check_bounds({"young_fat": [700, 2600], "angle": [40, 55]})
    assert bounds == {"young_fat": (700.0, 2600.0), "angle": (40.0, 55.0)}
    assert within_bounds(cc, bounds)  # bounds included; the angle binds mlo breasts only
    assert not within_bounds(mlo, bounds)
    assert within_bounds({**mlo, "angle": 55.0}, bounds)
    assert not within_bounds({**cc, "young_fat": 699.9}, bounds)
    assert within_bounds(cc, {}) and check_bounds(None) is None
    with pytest.raises(ValueError, match=r"data\.train_conditions\.view: unknown condition"):
        check_bounds({"view": ["cc", "cc"]})
    with pytest.raises(ValueError, match=r"data\.train_conditions\.friction must be \[low, high\]"):
        check_bounds({"friction": [True, 1]})
