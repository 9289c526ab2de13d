"""The LightningModule of the sequence surrogate: one shared step, errors in millimetres.

The network's settings have one home: the signature of `SurrogateModule`. The Hydra config
``model/att_blstm`` (conf/model/att_blstm.yaml) holds only the target and ``step:
${data.step}``; its other keys are the node ``model/att_blstm_signature``, generated from the
signature and stored in Hydra's ConfigStore when this module is imported (so whatever composes
conf/train.yaml imports it first: train.py, the benchmarks, the tests). The keys are listed,
so ``python train.py model.hidden=128`` needs no ``+``, and ``--cfg job`` shows every setting;
a default changed here is the config's default, with no YAML copy to disagree (a YAML that
restated the keys, kept equal by a test, would still be two homes). ``activations=None`` is
the paper's choice for the step (`mammo_net.models.PAPER_ACTIVATIONS`), and the number of
input features follows from the step (`datamodules.features.STEP_FEATURES`), so the network
cannot be built for other features than the data module's.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.config_store import ConfigStore
from numpy.typing import NDArray
from torch.nn import functional as F

from datamodules.features import STEP_FEATURES, FeatureSchema
from fem.contract.trajectory import reading_file
from mammo_net.metrics import BreastErrors
from mammo_net.models import PAPER_ACTIVATIONS, AttBLSTM

STAGES = ("train", "val", "test")

#: The leading bytes of every checkpoint: ``torch.save`` writes a ZIP archive.
CHECKPOINT_MAGIC = b"PK\x03\x04"


class SurrogateModule(L.LightningModule):
    """Att-BLSTM on per-node step sequences, (B, T, F) -> (B, T, 3), RMSE loss.

    The checkpoint holds everything to rebuild it (`from_checkpoint`): the hyperparameters,
    the feature standardisation (buffers ``feature_mean``/``feature_std``) and the feature
    schema (step, feature names, recorded steps; ``checkpoint["feature_schema"]``), both set
    from the training data with `set_feature_normalization` before fitting.

    Parameters
    ----------
    step : {"unloaded", "compression"}
        The simulation step it predicts; its features are the input (F = 11 or 22,
        `datamodules.features.STEP_FEATURES`).
    hidden, layers, dropout
        Of `mammo_net.models.AttBLSTM`.
    activations : (str, str), optional
        The attention layer's two stages; default the paper's for ``step``
        (`mammo_net.models.PAPER_ACTIVATIONS`: tanh, relu for the unloaded state; sigmoid,
        sigmoid for compression).
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
        step: str,
        hidden: int = 64,
        layers: int = 2,
        activations: Sequence[str] | None = None,
        dropout: float = 0.0,
        residual: bool = True,
        lr: float = 0.03,
        lr_schedule: str = "constant",
    ) -> None:
        super().__init__()
        if step not in STEP_FEATURES:
            raise ValueError(f"model.step must be one of {sorted(STEP_FEATURES)}, got {step!r}")
        if lr_schedule not in ("constant", "cosine"):
            raise ValueError(
                f"model.lr_schedule must be 'constant' or 'cosine', not {lr_schedule!r}"
            )
        if activations is None:
            activations = PAPER_ACTIVATIONS[step]
        # saved resolved and as plain types: a weights-only checkpoint keeps its network
        activations = tuple(str(a) for a in activations)
        self.save_hyperparameters()
        self.net = AttBLSTM(self.n_features, hidden, layers, activations, dropout)
        self.register_buffer("feature_mean", torch.zeros(self.n_features))
        self.register_buffer("feature_std", torch.ones(self.n_features))
        self.schema: FeatureSchema | None = None
        # keys f"{stage}_rmse": a ModuleDict key may not shadow a method (train)
        self.errors = torch.nn.ModuleDict({f"{stage}_rmse": BreastErrors() for stage in STAGES})

    @property
    def n_features(self) -> int:
        """F, the number of input features: the step's."""
        return len(STEP_FEATURES[self.hparams.step])

    def check_data_step(self, step: str) -> None:
        """Refuse data of another simulation step than the network's: other features.

        Raises
        ------
        ValueError
            Naming the settings to change, ``model.step`` and ``data.step``.
        """
        if step != self.hparams.step:
            raise ValueError(
                f"model.step={self.hparams.step} (a network of {self.n_features} features) does "
                f"not match data.step={step}: leave model.step at its default ${{data.step}} or "
                "set both to the same step"
            )

    def set_feature_normalization(self, mean: NDArray, std: NDArray, schema: FeatureSchema) -> None:
        """Standardise the features with the training split's statistics, (F,) each, and
        record the data's feature ``schema`` (refused if of another step, `check_data_step`)."""
        self.check_data_step(schema.step)
        self.feature_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.feature_std.copy_(torch.as_tensor(std, dtype=torch.float32).clamp_min(1e-6))
        self.schema = schema

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.schema is not None:
            checkpoint["feature_schema"] = self.schema.to_json()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "feature_schema" in checkpoint:
            self.schema = FeatureSchema.from_json(checkpoint["feature_schema"], "checkpoint")

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> SurrogateModule:
        """The trained network of a checkpoint, on the CPU, in eval mode.

        Reads the file with ``torch.load(weights_only=True)``: no code from it is run.
        Checkpoints written before the step was a setting (hyperparameter ``n_features``, no
        ``step``) take the step of their feature schema.

        Raises
        ------
        FileNotFoundError
            The file does not exist.
        ValueError
            An empty, truncated or corrupt file, or one that is not a checkpoint of this
            module (`fem.contract.trajectory.reading_file`); such an old checkpoint without a
            feature schema, or whose ``n_features`` is not its step's number of features.
        """
        with reading_file(path, "a Lightning checkpoint (.ckpt)", CHECKPOINT_MAGIC) as p:
            checkpoint = torch.load(p, map_location="cpu", weights_only=True)
        if not isinstance(checkpoint, dict) or not {"hyper_parameters", "state_dict"} <= set(
            checkpoint
        ):
            raise ValueError(
                f"{path}: not a checkpoint of a trained network: fields 'hyper_parameters' and "
                "'state_dict' expected"
            )
        hparams = dict(checkpoint["hyper_parameters"])
        if "n_features" in hparams:
            n_features = hparams.pop("n_features")
            if "feature_schema" not in checkpoint:
                raise ValueError(f"{path}: the checkpoint names no step (no feature schema)")
            step = FeatureSchema.from_json(checkpoint["feature_schema"], str(path)).step
            if n_features != len(STEP_FEATURES.get(step, ())):
                raise ValueError(
                    f"{path}: n_features={n_features} is not the number of features of the "
                    f"schema's step {step!r}"
                )
            hparams["step"] = step
        model = cls(**hparams)
        model.load_state_dict(checkpoint["state_dict"], strict=True)
        model.on_load_checkpoint(checkpoint)
        return model.eval()

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


def signature_defaults(cls: type) -> dict[str, Any]:
    """The arguments of ``cls`` that have a default, with it: the config node of its settings."""
    return {
        name: p.default
        for name, p in inspect.signature(cls).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


ConfigStore.instance().store(
    group="model", name="att_blstm_signature", node=signature_defaults(SurrogateModule)
)


def warmup_cosine(step: int, total: int, warmup_fraction: float = 0.01) -> float:
    """Learning-rate factor at optimiser step ``step`` of ``total``: linear warm-up over the
    first ``warmup_fraction`` of the steps, then half a cosine from 1 down to 0."""
    warmup = max(1, round(warmup_fraction * total))
    if step < warmup:
        return (step + 1) / warmup
    return 0.5 * (
        1.0 + math.cos(math.pi * min(step - warmup, total - warmup) / max(1, total - warmup))
    )
