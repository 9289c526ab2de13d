"""The trajectory DataModule: caches, patient splits, sequence batches and flat rows."""

import numpy as np
import pytest
from conftest import tiny_trajectory

from datamodules.trajectories import TrajectoryDataModule


@pytest.mark.parametrize("step, n_features, n_steps", [("unloaded", 11, 2), ("compression", 22, 3)])
def test_sequences_and_rows(trajectory_folder, step, n_features, n_steps):
    dm = TrajectoryDataModule(str(trajectory_folder), step=step, val_fraction=0.25, batch_size=7)
    dm.prepare_data()
    dm.setup()
    train = {b.patient for b in dm.train}
    val = {b.patient for b in dm.val}
    assert not train & val and len(train | val) == 12 and len(val) == 3
    assert len(dm.val) == 6  # both breasts of each validation patient
    x, y, breast, scale, node = next(iter(dm.train_dataloader()))
    assert x.shape == (7, n_steps, n_features) and y.shape == (7, n_steps, 3)  # (B, T, F)
    assert breast.shape == scale.shape == node.shape == (7,) and bool((scale > 0).all())
    assert len(set(node.tolist())) == 7  # dataset indices, for de-duplication
    features, targets = next(TrajectoryDataModule.rows(dm.val))
    assert features.shape == (5 * n_steps, n_features) and targets.shape == (5 * n_steps, 3)
    # The cached targets map back to the trajectory in millimetres.
    breast = dm.val[0]
    traj = tiny_trajectory()
    positions = traj.unloaded if step == "unloaded" else traj.compressed
    mm = breast.normalization().invert(np.asarray(breast.targets()))
    np.testing.assert_allclose(mm, positions.transpose(1, 0, 2), atol=1e-5)


def test_k_fold_and_cache_reuse(trajectory_folder):
    folds = []
    for k in range(4):
        dm = TrajectoryDataModule(str(trajectory_folder), n_folds=4, fold=k)  # a fold: k-fold
        dm.prepare_data()
        dm.setup()
        folds.append({b.patient for b in dm.val})
    assert dm.hparams.split == "k_fold"
    assert set().union(*folds) == set(range(12)) and sum(map(len, folds)) == 12
    assert TrajectoryDataModule(str(trajectory_folder)).hparams.split == "one_fold"
    with pytest.raises(ValueError, match="the one-fold split has none"):
        TrajectoryDataModule(str(trajectory_folder), split="one_fold", fold=2)
    with pytest.raises(ValueError, match=r"fold must be in 0\.\.3"):
        TrajectoryDataModule(str(trajectory_folder), n_folds=4, fold=4)
    stamp = (
        (trajectory_folder / "cache" / "compression" / "P0000_L.features.npy").stat().st_mtime_ns
    )
    dm.prepare_data()  # cached breasts are not redone
    assert (
        trajectory_folder / "cache" / "compression" / "P0000_L.features.npy"
    ).stat().st_mtime_ns == stamp
    # A re-simulated breast (another file) is re-cached, never read from its old features.
    traj = tiny_trajectory("L", patient=0, site="A")
    traj.compressed[-1, :, 2] -= 1.0
    traj.save(trajectory_folder / "P0000_L.npz")
    dm.prepare_data()
    breast = next(b for b in dm.breasts() if b.name == "P0000_L")
    mm = breast.normalization().invert(np.asarray(breast.targets()))
    np.testing.assert_allclose(mm[:, -1], traj.compressed[-1], atol=1e-5)


def test_a_partial_cohort_is_a_clear_error(tmp_path):
    for lat in "LR":  # one patient: the one-fold split has no validation patient
        tiny_trajectory(lat, patient=0, site="A").save(tmp_path / f"P0000_{lat}.npz")
    dm = TrajectoryDataModule(str(tmp_path))
    dm.prepare_data()
    with pytest.raises(ValueError, match="1 patients give an empty validation split"):
        dm.setup()


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="step must be one of"):
        TrajectoryDataModule(str(tmp_path), step="gravity")
    with pytest.raises(FileNotFoundError, match="no simulated trajectories"):
        TrajectoryDataModule(str(tmp_path)).prepare_data()
