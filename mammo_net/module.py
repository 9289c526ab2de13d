"""The LightningModule of the sequence surrogate: one shared step, errors in millimetres."""

from __future__ import annotations

import functools
import math

import lightning as L
import torch
from numpy.typing import NDArray
from torch.nn import functional as F

from datamodules.features import FeatureSchema
from mammo_net.metrics import BreastErrors
from mammo_net.models import AttBLSTM

STAGES = ("train", "val", "test")


class SurrogateModule(L.LightningModule):
    """Att-BLSTM on per-node step sequences, (B, T, F) -> (B, T, 3), RMSE loss.

    The checkpoint holds everything to rebuild it: the hyperparameters, the feature
    standardisation (buffers ``feature_mean``/``feature_std``) and the feature schema (step,
    feature names, recorded steps; ``checkpoint["feature_schema"]``), both set from the
    training data with `set_feature_normalization` before fitting.

    Parameters
    ----------
    n_features : int
        11 (unloaded state) or 22 (compression).
    hidden, layers, activations, dropout
        Of `mammo_net.models.AttBLSTM`.
    residual : bool
        Predict the displacement from the node's input coordinates (features 1-3) instead of
        the coordinates (our addition; the paper's model: ``False``).
    lr : float
        Adam learning rate (the paper: 0.03), the peak one with a schedule.
    lr_schedule : {"constant", "cosine"}
        ``"cosine"``: linear warm-up over the first 1 % of the optimiser steps, then cosine
        decay to zero at the last step of ``trainer.max_epochs`` (our addition: the paper's
        constant 0.03 diverges after about three epochs on the virtual cohort).
    """

    def __init__(
        self,
        n_features: int,
        hidden: int = 64,
        layers: int = 2,
        activations: tuple[str, str] = ("tanh", "relu"),
        dropout: float = 0.0,
        residual: bool = True,
        lr: float = 0.03,
        lr_schedule: str = "constant",
    ) -> None:
        super().__init__()
        if lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine', not {lr_schedule!r}")
        activations = tuple(str(a) for a in activations)  # plain types: weights-only checkpoints
        self.save_hyperparameters()
        self.net = AttBLSTM(n_features, hidden, layers, activations, dropout)
        self.register_buffer("feature_mean", torch.zeros(n_features))
        self.register_buffer("feature_std", torch.ones(n_features))
        self.schema: FeatureSchema | None = None
        # keys f"{stage}_rmse": a ModuleDict key may not shadow a method (train)
        self.errors = torch.nn.ModuleDict({f"{stage}_rmse": BreastErrors() for stage in STAGES})

    def set_feature_normalization(
        self, mean: NDArray, std: NDArray, schema: FeatureSchema | None = None
    ) -> None:
        """Standardise the features with the training split's statistics, (F,) each, and
        record the data's feature ``schema``."""
        self.feature_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.feature_std.copy_(torch.as_tensor(std, dtype=torch.float32).clamp_min(1e-6))
        self.schema = schema

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.schema is not None:
            checkpoint["feature_schema"] = self.schema.to_json()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "feature_schema" in checkpoint:
            self.schema = FeatureSchema.from_json(checkpoint["feature_schema"], "checkpoint")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.net((x - self.feature_mean) / self.feature_std)  # (B, T, 3)
        return out + x[..., :3] if self.hparams.residual else out

    def shared_step(self, batch: tuple, stage: str) -> torch.Tensor:
        x, y, breast, scale, node = batch  # (B, T, F), (B, T, 3), (B,), (B,), (B,)
        prediction = self(x)  # (B, T, 3)
        loss = torch.sqrt(F.mse_loss(prediction, y))
        self.log(
            f"{stage}/loss",
            loss,
            on_step=stage == "train",
            on_epoch=True,
            batch_size=len(x),
            sync_dist=True,
        )
        self.errors[f"{stage}_rmse"].update(prediction, y, breast, scale, node)
        return loss

    def training_step(self, batch: tuple, batch_idx: int) -> torch.Tensor:
        return self.shared_step(batch, "train")

    def validation_step(self, batch: tuple, batch_idx: int) -> torch.Tensor:
        return self.shared_step(batch, "val")

    def test_step(self, batch: tuple, batch_idx: int) -> torch.Tensor:
        return self.shared_step(batch, "test")

    def _log_errors(self, stage: str) -> None:
        for name, value in self.errors[f"{stage}_rmse"].compute().items():
            self.log(f"{stage}/rmse_{name}_mm", value, sync_dist=True)  # equal on all ranks
        self.errors[f"{stage}_rmse"].reset()

    def on_train_epoch_end(self) -> None:
        self._log_errors("train")

    def on_validation_epoch_end(self) -> None:
        self._log_errors("val")

    def on_test_epoch_end(self) -> None:
        self._log_errors("test")

    def configure_optimizers(self) -> torch.optim.Optimizer | dict:
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams.lr)
        if self.hparams.lr_schedule == "constant":
            return optimizer
        total = self.trainer.estimated_stepping_batches
        if not math.isfinite(total):
            raise ValueError("lr_schedule='cosine' needs a finite trainer.max_epochs or max_steps")
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer, functools.partial(warmup_cosine, total=int(total))
        )
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }


def warmup_cosine(step: int, total: int, warmup_fraction: float = 0.01) -> float:
    """Learning-rate factor at optimiser step ``step`` of ``total``: linear warm-up over the
    first ``warmup_fraction`` of the steps, then half a cosine from 1 down to 0."""
    warmup = max(1, round(warmup_fraction * total))
    if step < warmup:
        return (step + 1) / warmup
    return 0.5 * (
        1.0 + math.cos(math.pi * min(step - warmup, total - warmup) / max(1, total - warmup))
    )
