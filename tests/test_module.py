"""The sequence surrogate: shapes, training lowers the loss, the checkpoint rebuilds it."""

import lightning as L
import numpy as np
import pytest
import torch

from datamodules.features import FeatureSchema
from datamodules.trajectories import TrajectoryDataModule
from mammo_net.models import AttBLSTM
from mammo_net.module import SurrogateModule, warmup_cosine


@pytest.mark.parametrize("activations", [("tanh", "relu"), ("sigmoid", "sigmoid")])
def test_att_blstm_shapes(activations):
    net = AttBLSTM(22, hidden=8, layers=2, activations=activations)
    assert net(torch.zeros(5, 70, 22)).shape == (5, 70, 3)  # (B, T, F) -> (B, T, 3)
    with pytest.raises(ValueError, match="activation must be one of"):
        AttBLSTM(11, activations=("tanh", "gelu"))


def test_fit_log_and_reload(trajectory_folder, tmp_path):
    torch.manual_seed(0)
    dm = TrajectoryDataModule(
        str(trajectory_folder), step="compression", val_fraction=0.25, batch_size=16
    )
    dm.prepare_data()
    dm.setup()
    model = SurrogateModule(22, hidden=8, layers=1, lr=0.01)
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
    again = SurrogateModule.load_from_checkpoint(ckpt, weights_only=True)
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
    model = SurrogateModule(11, hidden=4, layers=1, lr=0.01, lr_schedule="cosine")
    trainer = L.Trainer(
        max_epochs=2, accelerator="cpu", logger=False, enable_progress_bar=False,
        enable_checkpointing=False, default_root_dir=tmp_path,
    )  # fmt: skip
    trainer.fit(model, dm)
    lr = trainer.optimizers[0].param_groups[0]["lr"]
    assert lr < 0.01 * 0.01  # the last step's factor, near zero
    with pytest.raises(ValueError, match="lr_schedule must be"):
        SurrogateModule(11, lr_schedule="linear")
