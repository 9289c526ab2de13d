"""The prediction API: models load with their schema, and predict_breast builds the same
features as the training caches, batched over thicknesses."""

from dataclasses import replace

import lightning as L
import numpy as np
import pytest
import torch
from conftest import tiny_trajectory

from datamodules.features import FeatureSchema, compression_features, unloaded_features
from datamodules.trajectories import TrajectoryDataModule
from fem.simulate import plate_schedule
from fem.trajectory import NodeFlag
from mammo_net import baselines
from mammo_net.module import SurrogateModule
from mammo_net.predictor import load_surrogate, predict_breast


def scheduled_trajectory(thickness=0.7, patient=0):
    """The tiny trajectory with its plates where the FE puts them for ``thickness``."""
    t = tiny_trajectory("R", patient=patient, site="AB"[patient % 2])
    flags = t.node_flags.copy()
    flags[4] |= NodeFlag.MUSCLE_INTERFACE
    t = replace(t, node_flags=flags)
    plates, ratio = plate_schedule(t, t.unloaded[-1], thickness).recorded(len(t.compressed))
    return replace(t, plates=plates, compression_ratio=ratio)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A tiny network (unloaded state) and XGBoost (compression), saved with their schemas."""
    folder = tmp_path_factory.mktemp("models")
    data = folder / "trajectories"
    data.mkdir()
    for p in range(8):
        scheduled_trajectory(0.6 + 0.02 * p, p).save(data / f"P{p:04d}_R.npz")
    dm = TrajectoryDataModule(str(data), step="unloaded", batch_size=8, val_fraction=0.25)
    dm.prepare_data()
    dm.setup()
    torch.manual_seed(0)
    net = SurrogateModule(11, hidden=4, layers=1)
    net.set_feature_normalization(*dm.feature_statistics(), dm.schema())
    trainer = L.Trainer(max_epochs=1, accelerator="cpu", logger=False, enable_progress_bar=False,
                        enable_checkpointing=False, default_root_dir=folder)  # fmt: skip
    trainer.fit(net, dm)
    trainer.save_checkpoint(folder / "unloaded.ckpt")
    cdm = TrajectoryDataModule(str(data), step="compression", val_fraction=0.25)
    cdm.prepare_data()
    cdm.setup()
    X, Y = baselines.stack_rows(cdm.rows(cdm.train))
    booster = baselines.fit_xgboost(X, Y, n_estimators=5, max_depth=3, n_jobs=1)
    baselines.save_xgboost(booster, folder / "compression.json", cdm.schema())
    baselines.save_xgboost(booster, folder / "no_schema.json")
    return folder


def test_predictions_use_the_training_features(models):
    unloaded = load_surrogate(models / "unloaded.ckpt", "unloaded")
    compression = load_surrogate(models / "compression.json", "compression")
    assert unloaded.schema == FeatureSchema.of("unloaded", 2)
    assert compression.schema == FeatureSchema.of("compression", 3)
    traj = scheduled_trajectory(0.7)
    # With the FE unloaded shape, the compression features are the cached ones exactly.
    fe = predict_breast(traj, None, compression, [0.7])
    features, _, norm = compression_features(traj)
    expected = norm.invert(compression.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    np.testing.assert_allclose(fe.compressed[0], expected, atol=1e-5)
    np.testing.assert_allclose(fe.compression_ratio[0], traj.compression_ratio)
    # The unloaded-state model's steps, then several thicknesses in one batched call.
    shapes = predict_breast(traj, unloaded, compression, [0.5, 0.7, 0.9])
    features, _, norm = unloaded_features(traj)
    expected = norm.invert(unloaded.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    np.testing.assert_allclose(shapes.unloaded, expected, atol=1e-5)
    assert shapes.compressed.shape == (3, 3, 5, 3) and shapes.plates.shape == (3, 3, 2, 2)
    one = predict_breast(traj, unloaded, compression, [0.9])
    np.testing.assert_allclose(shapes.compressed[2], one.compressed[0], atol=1e-5)
    assert shapes.compression_ratio[:, -1].argsort().tolist() == [2, 1, 0]  # thinner: more


def test_wrong_models_and_thicknesses_are_refused(models):
    with pytest.raises(ValueError, match="predicts the unloaded step, not the compression step"):
        load_surrogate(models / "unloaded.ckpt", "compression")
    with pytest.raises(ValueError, match=r"no_schema.json: the file has no feature schema"):
        load_surrogate(models / "no_schema.json")
    with pytest.raises(ValueError, match="a model file ends in one of"):
        load_surrogate(models / "model.pkl")
    unloaded = load_surrogate(models / "unloaded.ckpt")
    compression = load_surrogate(models / "compression.json")
    with pytest.raises(
        ValueError, match="compression model att_blstm: the model predicts the unloaded"
    ):
        predict_breast(scheduled_trajectory(), unloaded, unloaded, [0.7])
    with pytest.raises(ValueError, match="is not smaller than the breast's cranio-caudal extent"):
        predict_breast(scheduled_trajectory(), None, compression, [5.0])
