"""The sequence surrogate: shapes, training lowers the loss, the checkpoint rebuilds it."""

from dataclasses import replace
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from datamodules.features import STEP_FEATURES, FeatureSchema
from datamodules.trajectories import TrajectoryDataModule
from mammo_net.models import PAPER_ACTIVATIONS, AttBLSTM
from mammo_net.module import SurrogateModule, warmup_cosine
from mammo_net.predictor import load_surrogate


@pytest.mark.parametrize("activations", [("tanh", "relu"), ("sigmoid", "sigmoid")])
def test_att_blstm_shapes(activations):
    net = AttBLSTM(22, hidden=8, layers=2, activations=activations, dropout=0.0)
    assert net(torch.zeros(5, 70, 22)).shape == (5, 70, 3)  # (B, T, F) -> (B, T, 3)
    with pytest.raises(ValueError, match="activation must be one of"):
        AttBLSTM(11, hidden=8, layers=1, activations=("tanh", "gelu"), dropout=0.0)


def test_the_step_sets_the_features_and_the_paper_activations():
    for step, activations in PAPER_ACTIVATIONS.items():
        model = SurrogateModule(step, hidden=4, layers=1)
        assert model.hparams.activations == activations
        assert model.n_features == len(STEP_FEATURES[step]) == len(model.feature_mean)
        assert model.net.encoder.input_size == model.n_features
    own = SurrogateModule("unloaded", hidden=4, layers=1, activations=["sigmoid", "tanh"])
    assert own.hparams.activations == ("sigmoid", "tanh")
    with pytest.raises(ValueError, match="step must be one of"):
        SurrogateModule("compressed")
    with pytest.raises(ValueError, match=r"model\.step=compression .*data\.step=unloaded"):
        SurrogateModule("compression").set_feature_normalization(
            np.zeros(11), np.ones(11), FeatureSchema.of("unloaded", 2)
        )


def old_format_checkpoint(step: str, folder: Path) -> Path:
    """A checkpoint as the cross-validation folds were saved before 2026-12-05: hyperparameter
    ``n_features`` and no ``step``, no network name, a feature schema without revisions."""
    model = SurrogateModule(step, hidden=4, layers=1)
    hparams = dict(model.hparams)
    del hparams["step"]
    old_schema = replace(FeatureSchema.of(step, 5), revisions=())
    path = folder / f"old_{step}.ckpt"
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": {"n_features": model.n_features, **hparams},
            "feature_schema": old_schema.to_json(),
        },
        path,
    )
    return path


def test_old_compression_checkpoints_are_refused_as_stale(tmp_path):
    """Compression checkpoints trained before the plate edges were redefined
    (`datamodules.features.REVISIONS`) load, and are refused for prediction."""
    path = old_format_checkpoint("compression", tmp_path)
    model = SurrogateModule.from_checkpoint(path)
    assert model.schema.revisions == ()
    with pytest.raises(
        ValueError, match=r"old_compression\.ckpt: .*upper_plate_edge_y 1 -> 2.*retrain"
    ):
        load_surrogate(path)


@pytest.mark.parametrize("step", ["compression", "unloaded"])
def test_old_format_checkpoints_load(step, tmp_path):
    """Checkpoints saved with ``n_features`` and no step take their step from the feature
    schema."""
    path = old_format_checkpoint(step, tmp_path)
    checkpoint = torch.load(path, weights_only=True)
    assert "step" not in checkpoint["hyper_parameters"]  # the format before the step setting
    model = SurrogateModule.from_checkpoint(path)
    assert model.hparams.step == model.schema.step == step
    assert model.hparams.activations == PAPER_ACTIVATIONS[step]
    assert model.n_features == len(STEP_FEATURES[step]) == (22 if step == "compression" else 11)
    assert not model.training
    with torch.no_grad():
        out = model(torch.zeros(2, model.schema.n_steps, model.n_features))
    assert out.shape == (2, model.schema.n_steps, 3)
    checkpoint["hyper_parameters"]["n_features"] = 33  # not the step's
    torch.save(checkpoint, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match=f"n_features=33 is not .* step '{step}'"):
        SurrogateModule.from_checkpoint(tmp_path / "other.ckpt")
    del checkpoint["feature_schema"]
    torch.save(checkpoint, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="names no step"):
        SurrogateModule.from_checkpoint(tmp_path / "other.ckpt")


def test_fit_log_and_reload(trajectory_folder, tmp_path):
    torch.manual_seed(0)
    dm = TrajectoryDataModule(
        str(trajectory_folder), step="compression", val_fraction=0.25, batch_size=16
    )
    dm.prepare_data()
    dm.setup()
    model = SurrogateModule("compression", hidden=8, layers=1, lr=0.01)
    mean, std = dm.feature_statistics()
    model.set_feature_normalization(mean, std, dm.schema())
    trainer = L.Trainer(
        max_epochs=3,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        default_root_dir=tmp_path,
    )
    trainer.fit(model, dm)
    metrics = trainer.callback_metrics
    for name in (
        "train/loss",
        "val/loss",
        "val/rmse_all_steps_mean_mm",
        "val/rmse_last_step_median_mm",
    ):
        assert name in metrics and torch.isfinite(metrics[name])
    ckpt = tmp_path / "model.ckpt"
    trainer.save_checkpoint(ckpt)
    again = SurrogateModule.from_checkpoint(ckpt)
    assert again.schema == FeatureSchema.of("compression", 3)  # tiny trajectories: 3 steps
    np.testing.assert_array_equal(again.feature_mean.numpy(), mean.astype(np.float32))
    x = next(iter(dm.val_dataloader()))[0]
    model.eval(), again.eval()
    with torch.no_grad():
        torch.testing.assert_close(again(x), model(x), rtol=0, atol=0)


def test_cosine_schedule_warms_up_and_decays_to_zero(trajectory_folder, tmp_path):
    assert warmup_cosine(0, 1000) == pytest.approx(0.1)  # warm-up over 10 steps
    assert warmup_cosine(9, 1000) == pytest.approx(1.0)
    assert warmup_cosine(10 + 495, 1000) == pytest.approx(0.5)
    assert warmup_cosine(1000, 1000) == pytest.approx(0.0)
    dm = TrajectoryDataModule(str(trajectory_folder), step="unloaded", batch_size=16)
    model = SurrogateModule("unloaded", hidden=4, layers=1, lr=0.01, lr_schedule="cosine")
    trainer = L.Trainer(
        max_epochs=2, accelerator="cpu", logger=False, enable_progress_bar=False,
        enable_checkpointing=False, default_root_dir=tmp_path,
    )  # fmt: skip
    trainer.fit(model, dm)
    lr = trainer.optimizers[0].param_groups[0]["lr"]
    assert lr < 0.01 * 0.01  # the last step's factor, near zero
    with pytest.raises(ValueError, match="lr_schedule must be"):
        SurrogateModule("unloaded", lr_schedule="linear")
