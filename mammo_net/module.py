"""The LightningModules of the networks: one shared step each, errors in millimetres.

`NetworkModule` holds what every network shares (the step it predicts, the input schema it was
trained on, the ``train/…``, ``val/…``, ``test/…`` metrics, the optimiser and its schedule,
loading a checkpoint safely); `SurrogateModule` is the paper's Att-BLSTM on per-node step
sequences, `MeshGraphModule` the mesh-aware graph network on whole breasts
(`mammo_net.models.MeshGraphNet`, data from `datamodules.graphs`).

A network's settings have one home: the signature of its class. The Hydra config
``model/att_blstm`` (conf/model/att_blstm.yaml) holds only the target and ``step:
${data.step}``; its other keys are the node ``model/att_blstm_signature``, generated from the
signature and stored in Hydra's ConfigStore when this module is imported (so whatever composes
conf/train.yaml imports it first: train.py, the benchmarks, the tests). The keys are listed,
so ``python train.py model.hidden=128`` needs no ``+``, and ``--cfg job`` shows every setting;
a default changed here is the config's default, with no YAML copy to disagree (a YAML that
restated the keys, kept equal by a test, would still be two homes). ``model/mesh_gnn`` and
``model/mesh_gnn_signature`` do the same for `MeshGraphModule`. ``activations=None`` is
the paper's choice for the step (`mammo_net.models.PAPER_ACTIVATIONS`), and the number of
input features follows from the step (`datamodules.features.STEP_FEATURES`), so the network
cannot be built for other features than the data module's.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.config_store import ConfigStore
from numpy.typing import NDArray
from torch.nn import functional as F

from datamodules.features import STEP_FEATURES, FeatureSchema
from datamodules.graphs import (
    CONDITION_FEATURES,
    NODE_FEATURES,
    NODE_STEP_INPUTS,
    STEP_INPUTS,
    MeshGraphDataModule,
    graph_inputs,
    stiffness_bounds,
)
from fem.contract.trajectory import reading_file
from mammo_net.inference import graph_predictor, network_predictor
from mammo_net.metrics import BreastErrors
from mammo_net.models import PAPER_ACTIVATIONS, AttBLSTM, MeshGraphNet

#: The batch entries `MeshGraphNet.forward` takes, in order.
GRAPH_INPUTS = ("nodes", "edges", "graph", "steps", "node_steps", "conditions")

STAGES = ("train", "val", "test")

#: The leading bytes of every checkpoint: ``torch.save`` writes a ZIP archive.
CHECKPOINT_MAGIC = b"PK\x03\x04"


class NetworkModule(L.LightningModule):
    """What every network shares: its simulation step, the input schema of its training data
    (``checkpoint["feature_schema"]``), the per-breast RMSE metrics of each stage, Adam with
    an optional warm-up and cosine schedule, and `from_checkpoint`.

    Subclasses set ``name`` (the predictions file and the table's row), save their
    hyperparameters (``step``, ``lr``, ``lr_schedule`` among them) and define `adapt` (take
    what the network needs from the data module before fitting) and `shared_step`.
    """

    name = "network"
    #: Settings of the fit, not of the network: a fine-tune (`start_from`) may change them.
    fit_settings = ("lr", "lr_schedule", "train_steps")

    def __init__(self) -> None:
        super().__init__()
        self.schema: FeatureSchema | None = None
        # keys f"{stage}_rmse": a ModuleDict key may not shadow a method (train)
        self.errors = torch.nn.ModuleDict({f"{stage}_rmse": BreastErrors() for stage in STAGES})

    @staticmethod
    def check_settings(step: str, lr_schedule: str) -> None:
        """Refuse an unknown step or learning-rate schedule, naming the setting."""
        if step not in STEP_FEATURES:
            raise ValueError(f"model.step must be one of {sorted(STEP_FEATURES)}, got {step!r}")
        if lr_schedule not in ("constant", "cosine"):
            raise ValueError(
                f"model.lr_schedule must be 'constant' or 'cosine', not {lr_schedule!r}"
            )

    def check_data_step(self, step: str) -> None:
        """Refuse data of another simulation step than the network's: other inputs.

        Raises
        ------
        ValueError
            Naming the settings to change, ``model.step`` and ``data.step``.
        """
        if step != self.hparams.step:
            raise ValueError(
                f"model.step={self.hparams.step} ({self.name} of the {self.hparams.step} step's "
                f"inputs) does not match data.step={step}: leave model.step at its default "
                "${data.step} or set both to the same step"
            )

    def adapt(self, dm: L.LightningDataModule) -> None:
        """Take what the network needs from the data module ``dm`` (set up) before fitting."""
        raise NotImplementedError

    def predictor(self, precision: str = "32-true") -> Callable[[Any], NDArray]:
        """A cached breast's inputs (``Breast.features()``) to its normalised coordinates
        (N, T, 3) (`mammo_net.inference`)."""
        raise NotImplementedError

    @property
    def takes_graphs(self) -> bool:
        """Whether its inputs are whole-breast graphs (`datamodules.graphs`), not node rows."""
        return False

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["network"] = self.name
        if self.schema is not None:
            checkpoint["feature_schema"] = self.schema.to_json()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "feature_schema" in checkpoint:
            self.schema = FeatureSchema.from_json(checkpoint["feature_schema"], "checkpoint")

    @classmethod
    def upgrade_hparams(cls, hparams: dict, checkpoint: dict, path: str | Path) -> dict:
        """The constructor arguments of a checkpoint's stored hyperparameters (older
        checkpoints' names mapped to today's); as stored by default."""
        return hparams

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> NetworkModule:
        """The trained network of a checkpoint, on the CPU, in eval mode: of the class its
        ``checkpoint["network"]`` names (`NETWORKS`; checkpoints written before there were
        two networks are Att-BLSTMs), which must be ``cls`` or a subclass of it
        (``NetworkModule.from_checkpoint`` loads any).

        Reads the file with ``torch.load(weights_only=True)``: no code from it is run.

        Raises
        ------
        FileNotFoundError
            The file does not exist.
        ValueError
            An empty, truncated or corrupt file, or one that is not a checkpoint of this
            module (`fem.contract.trajectory.reading_file`), or whose stored settings this
            module refuses.
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
        name = checkpoint.get("network", SurrogateModule.name)
        network = NETWORKS.get(name) if isinstance(name, str) else None
        if network is None or not issubclass(network, cls):
            raise ValueError(f"{path}: a checkpoint of the network {name!r}, not a {cls.__name__}")
        hparams = network.upgrade_hparams(dict(checkpoint["hyper_parameters"]), checkpoint, path)
        try:
            model = network(**hparams)
            model.load_state_dict(checkpoint["state_dict"], strict=True)
        except (TypeError, RuntimeError) as exc:  # another network's settings or weights
            raise ValueError(f"{path}: not a checkpoint of {cls.__name__} ({exc})") from exc
        model.on_load_checkpoint(checkpoint)
        return model.eval()

    def start_from(self, path: str | Path) -> None:
        """Take the weights (and the buffers: a feature normalisation) of a trained network's
        checkpoint, read by `from_checkpoint`, to fit on from them (fine-tuning, e.g. on
        breasts meshed at other resolutions: the optimizer, the schedule and the epochs start
        afresh). Call it after `adapt`, so that the stored normalisation stays the weights'.

        Raises
        ------
        ValueError
            Another network, step or architecture than this one's; the message names the
            file and the settings.
        """
        trained = NetworkModule.from_checkpoint(path)
        if type(trained) is not type(self) or trained.hparams.step != self.hparams.step:
            raise ValueError(
                f"{path}: a {trained.name} of the {trained.hparams.step} step; init_from must "
                f"name a {self.name} of the {self.hparams.step} step (model=, data.step=)"
            )
        network = set(self.hparams) | set(trained.hparams)
        differ = sorted(
            k
            for k in network - set(self.fit_settings)
            if self.hparams.get(k) != trained.hparams.get(k)
        )
        if differ:
            raise ValueError(
                f"{path}: its network was built with other settings: "
                + ", ".join(
                    f"model.{k}={trained.hparams.get(k)!r} (here {self.hparams.get(k)!r})"
                    for k in differ
                )
            )
        self.load_state_dict(trained.state_dict(), strict=True)  # equal settings: same shapes

    def shared_step(self, batch: Any, stage: str) -> torch.Tensor:
        raise NotImplementedError

    def log_loss(self, loss: torch.Tensor, stage: str, batch_size: int) -> None:
        self.log(
            f"{stage}/loss",
            loss,
            on_step=stage == "train",
            on_epoch=True,
            batch_size=batch_size,
            sync_dist=True,
        )

    def training_step(self, batch: Any, batch_idx: int) -> torch.Tensor:
        return self.shared_step(batch, "train")

    def validation_step(self, batch: Any, batch_idx: int) -> torch.Tensor:
        return self.shared_step(batch, "val")

    def test_step(self, batch: Any, batch_idx: int) -> torch.Tensor:
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


class SurrogateModule(NetworkModule):
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

    name = "att_blstm"

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
        self.check_settings(step, lr_schedule)
        if activations is None:
            activations = PAPER_ACTIVATIONS[step]
        # saved resolved and as plain types: a weights-only checkpoint keeps its network
        activations = tuple(str(a) for a in activations)
        self.save_hyperparameters()
        self.net = AttBLSTM(self.n_features, hidden, layers, activations, dropout)
        self.register_buffer("feature_mean", torch.zeros(self.n_features))
        self.register_buffer("feature_std", torch.ones(self.n_features))

    @property
    def n_features(self) -> int:
        """F, the number of input features: the step's."""
        return len(STEP_FEATURES[self.hparams.step])

    def adapt(self, dm: L.LightningDataModule) -> None:
        """The training split's feature statistics and schema (`set_feature_normalization`)."""
        if isinstance(dm, MeshGraphDataModule):
            raise ValueError(
                "model=att_blstm trains on node sequences (data=default), not on whole-breast "
                "graphs (data=graphs)"
            )
        self.set_feature_normalization(*dm.feature_statistics(), dm.schema())

    def predictor(self, precision: str = "32-true") -> Callable[[NDArray], NDArray]:
        return network_predictor(self, precision=precision)

    def set_feature_normalization(self, mean: NDArray, std: NDArray, schema: FeatureSchema) -> None:
        """Standardise the features with the training split's statistics, (F,) each, and
        record the data's feature ``schema`` (refused if of another step, `check_data_step`)."""
        self.check_data_step(schema.step)
        self.feature_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.feature_std.copy_(torch.as_tensor(std, dtype=torch.float32).clamp_min(1e-6))
        self.schema = schema

    @classmethod
    def upgrade_hparams(cls, hparams: dict, checkpoint: dict, path: str | Path) -> dict:
        """Checkpoints written before the step was a setting (hyperparameter ``n_features``,
        no ``step``) take the step of their feature schema.

        Raises
        ------
        ValueError
            Such a checkpoint without a feature schema, or whose ``n_features`` is not its
            step's number of features.
        """
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
        return hparams

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.net((x - self.feature_mean) / self.feature_std)  # (B, T, 3)
        return out + x[..., :3] if self.hparams.residual else out

    def shared_step(self, batch: tuple, stage: str) -> torch.Tensor:
        x, y, breast, scale, node = batch  # (B, T, F), (B, T, 3), (B,), (B,), (B,)
        prediction = self(x)  # (B, T, 3)
        loss = torch.sqrt(F.mse_loss(prediction, y))
        self.log_loss(loss, stage, len(x))
        self.errors[f"{stage}_rmse"].update(prediction, y, breast, scale, node)
        return loss


#: `MeshGraphModule.compliance_scaling`'s tissues: (node indicator column, log-modulus
#: condition column) of fat and gland, the tissues that carry the body load.
COMPLIANCE_COLUMNS = tuple(
    (NODE_FEATURES.index(bit), CONDITION_FEATURES.index(f"log_young_{tissue}"))
    for bit, tissue in (("tissue_bit_1_fat", "fat"), ("tissue_bit_2_gland", "gland"))
)


class MeshGraphModule(NetworkModule):
    """The mesh-aware surrogate: `mammo_net.models.MeshGraphNet` on whole breast graphs
    (`datamodules.graphs`), every node's trajectory of a step in one pass, (T, N, 3); RMSE
    loss over nodes and steps, in normalised units (equation 1).

    Its inputs are fixed by the step (`datamodules.graphs.graph_inputs`) and need no
    statistics: coordinates are z-scored per breast, stiffness enters as log-ratios to the
    paper's, flags as bits. The checkpoint holds the hyperparameters and the data's schema.

    Parameters
    ----------
    step : {"unloaded", "compression"}
        The simulation step it predicts.
    hidden, layers, slices, heads, decoder_hidden
        Of `mammo_net.models.MeshGraphNet` (``slices=0``: no global attention path).
    train_steps : int, optional
        Decode only this many of a batch's recorded steps in a training step: a fresh random
        sample each time, always with the last step (the processor pass is the same for all
        steps, and the decoder's (T, N) grid is most of a step's cost); ``train/…`` errors are
        then over the sampled steps. ``None``: every step.
    knots : int, optional
        Validation, tests and predictions decode this many evenly spaced steps and
        interpolate the others linearly, from the input shape on (`mammo_net.models.step_knots`;
        about 0.01 mm RMS added on the FE's own compression trajectories with 20 of 70 steps);
        ``None``: decode every step.
    compliance_scaling : bool, optional
        Multiply the decoded displacement by the breast's linear-elastic compliance over its
        fat and gland (`mammo_net.models.compliance_gain`): the network then learns the
        displacement per unit compliance and extrapolates to softer or stiffer tissue as 1/E,
        as a body load's displacement does. ``None``: on for the unloaded state (gravity),
        off for the compression (driven by the plates' travel). With the paper's materials
        the gain is 1. Checkpoints written before the setting existed load without it.
    stiffness_range : bool, optional
        Record the training breasts' range of every tissue's modulus (`adapt`,
        `datamodules.graphs.stiffness_bounds`; the buffer ``net.condition_bounds``) and show
        the network a breast outside it scaled uniformly into it
        (`mammo_net.models.scaled_into_range`): the compliance gain, on the breast's own
        moduli, then extrapolates as a linear-elastic body does, not the network. Needs
        ``compliance_scaling``. ``None``: with it. Stored resolved; checkpoints written
        before the setting existed load without it (`mammo_net.stiffness_range` records the
        range in one).
    lr, lr_schedule
        As `SurrogateModule`'s.
    """

    name = "mesh_gnn"

    def __init__(
        self,
        step: str,
        hidden: int = 48,
        layers: int = 4,
        slices: int = 16,
        heads: int = 4,
        decoder_hidden: int = 48,
        train_steps: int | None = 16,
        knots: int | None = 20,
        compliance_scaling: bool | None = None,
        stiffness_range: bool | None = None,
        lr: float = 0.001,
        lr_schedule: str = "cosine",
    ) -> None:
        super().__init__()
        self.check_settings(step, lr_schedule)
        if train_steps is not None and train_steps < 1:
            raise ValueError(f"model.train_steps must be at least 1 (or null), got {train_steps}")
        if knots is not None and knots < 1:
            raise ValueError(f"model.knots must be at least 1 (or null), got {knots}")
        self.save_hyperparameters()
        if stiffness_range is None:
            self.hparams.stiffness_range = self.scales_compliance
        elif stiffness_range and not self.scales_compliance:
            raise ValueError(
                "model.stiffness_range=true needs the compliance gain that extrapolates "
                f"beyond the range: model.compliance_scaling=true (the {step} step's "
                "default is off)"
            )
        self.net = MeshGraphNet(
            len(NODE_FEATURES),
            len(STEP_INPUTS[step]),
            len(NODE_STEP_INPUTS[step]),
            len(CONDITION_FEATURES),
            hidden,
            layers,
            slices,
            heads,
            decoder_hidden,
            COMPLIANCE_COLUMNS if self.scales_compliance else (),
            bounded=self.hparams.stiffness_range,
        )

    @property
    def scales_compliance(self) -> bool:
        """Whether the decoded displacement is scaled (`compliance_scaling`, resolved)."""
        setting = self.hparams.compliance_scaling
        return self.hparams.step == "unloaded" if setting is None else bool(setting)

    @classmethod
    def upgrade_hparams(cls, hparams: dict, checkpoint: dict, path: str | Path) -> dict:
        """Checkpoints written before `compliance_scaling` or `stiffness_range` existed were
        trained without them."""
        return {"compliance_scaling": False, "stiffness_range": False, **hparams}

    def adapt(self, dm: L.LightningDataModule) -> None:
        """Record the data's schema (graph inputs of the model's step, refused otherwise)
        and, with `stiffness_range`, the training breasts' range of the moduli."""
        if not isinstance(dm, MeshGraphDataModule):
            raise ValueError(
                "model=mesh_gnn trains on whole-breast graphs: set data=graphs "
                "(conf/data/graphs.yaml), or experiment=mesh_gnn"
            )
        schema = dm.schema()
        self.check_data_step(schema.step)
        schema.check(self.hparams.step, "data", graph_inputs(self.hparams.step))
        self.schema = schema
        if self.net.bounded:
            self.net.condition_bounds.copy_(stiffness_bounds(dm.train))

    @property
    def takes_graphs(self) -> bool:
        return True

    def predictor(self, precision: str = "32-true") -> Callable[[Any], NDArray]:
        return graph_predictor(self, precision=precision)

    def forward(
        self, batch: dict[str, torch.Tensor], decoded: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Coordinates (T, N, 3) of a `datamodules.graphs.batch_graphs` batch: at the step
        indices ``decoded`` only, when given, else every step, decoded at ``knots``."""
        inputs = (batch[k] for k in GRAPH_INPUTS)
        return self.net(*inputs, decoded=decoded, knots=self.hparams.get("knots"))

    def sampled_steps(self, n_steps: int) -> torch.Tensor | None:
        """The step indices a training step decodes (`train_steps`), sorted, the last
        included; ``None`` for all."""
        k = self.hparams.train_steps
        if k is None or k >= n_steps:
            return None
        others = torch.randperm(n_steps - 1, device=self.device)[: k - 1]
        return torch.cat([others.sort().values, others.new_tensor([n_steps - 1])])

    def shared_step(self, batch: dict[str, torch.Tensor], stage: str) -> torch.Tensor:
        y = batch["targets"]  # (T, N, 3)
        decoded = self.sampled_steps(len(y)) if stage == "train" else None
        if decoded is not None:
            y = y[decoded]
        prediction = self(batch, decoded)  # (T, N, 3)
        loss = torch.sqrt(F.mse_loss(prediction, y))
        self.log_loss(loss, stage, int(batch["conditions"].shape[0]))
        self.errors[f"{stage}_rmse"].update(
            prediction.transpose(0, 1),
            y.transpose(0, 1),
            batch["breast"],
            batch["scale"],
            batch["node"],
        )
        return loss


def signature_defaults(cls: type) -> dict[str, Any]:
    """The arguments of ``cls`` that have a default, with it: the config node of its settings."""
    return {
        name: p.default
        for name, p in inspect.signature(cls).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


#: The networks by name (``checkpoint["network"]``, the model config's name).
NETWORKS: dict[str, type[NetworkModule]] = {
    SurrogateModule.name: SurrogateModule,
    MeshGraphModule.name: MeshGraphModule,
}

for _name, _module in NETWORKS.items():
    ConfigStore.instance().store(
        group="model", name=f"{_name}_signature", node=signature_defaults(_module)
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
