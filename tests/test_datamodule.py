"""The trajectory DataModule: caches, patient splits, sequence batches and flat rows."""

import numpy as np
import pytest
from conftest import tiny_trajectory

from datamodules.trajectories import TrajectoryDataModule


@pytest.fixture
def folder(tmp_path):
    """12 patients (3 of site A), both breasts each: tiny simulated trajectories."""
    for p in range(12):
        for lat in "LR":
            site = "A" if p % 4 == 0 else "B"
            tiny_trajectory(lat, patient=p, site=site).save(tmp_path / f"P{p:04d}_{lat}.npz")
    return tmp_path


@pytest.mark.parametrize("step, n_features, n_steps", [("unloaded", 11, 2), ("compression", 22, 3)])
def test_sequences_and_rows(folder, step, n_features, n_steps):
    dm = TrajectoryDataModule(str(folder), step=step, val_fraction=0.25, batch_size=7)
    dm.prepare_data()
    dm.setup()
    train = {b.patient for b in dm.train}
    val = {b.patient for b in dm.val}
    assert not train & val and len(train | val) == 12 and len(val) == 3
    assert len(dm.val) == 6  # both breasts of each validation patient
    x, y, breast, scale = next(iter(dm.train_dataloader()))
    assert x.shape == (7, n_steps, n_features) and y.shape == (7, n_steps, 3)  # (B, T, F)
    assert breast.shape == scale.shape == (7,) and bool((scale > 0).all())
    features, targets = next(TrajectoryDataModule.rows(dm.val))
    assert features.shape == (5 * n_steps, n_features) and targets.shape == (5 * n_steps, 3)
    # The cached targets map back to the trajectory in millimetres.
    breast = dm.val[0]
    traj = tiny_trajectory()
    positions = traj.unloaded if step == "unloaded" else traj.compressed
    mm = breast.normalization().invert(np.asarray(breast.targets()))
    np.testing.assert_allclose(mm, positions.transpose(1, 0, 2), atol=1e-5)


def test_k_fold_and_cache_reuse(folder):
    folds = []
    for k in range(4):
        dm = TrajectoryDataModule(str(folder), split="k_fold", n_folds=4, fold=k)
        dm.prepare_data()
        dm.setup()
        folds.append({b.patient for b in dm.val})
    assert set().union(*folds) == set(range(12)) and sum(map(len, folds)) == 12
    stamp = (folder / "cache" / "compression" / "P0000_L.features.npy").stat().st_mtime_ns
    dm.prepare_data()  # cached breasts are not redone
    assert (folder / "cache" / "compression" / "P0000_L.features.npy").stat().st_mtime_ns == stamp


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="step must be one of"):
        TrajectoryDataModule(str(tmp_path), step="gravity")
    with pytest.raises(FileNotFoundError, match="no simulated trajectories"):
        TrajectoryDataModule(str(tmp_path)).prepare_data()
