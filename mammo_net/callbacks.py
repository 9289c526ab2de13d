"""Lightning callbacks that fit the tree baselines beside the network, in the same run.

At the start of fitting a callback fits its model on the DataModule's training rows; at the
end of fitting (and of testing) it predicts the validation breasts with the same metric code
as the network and logs ``val/rmse_<name>_mm/<model>`` next to the network's
``val/rmse_<name>_mm``. The fitted model is saved in a non-pickle
format (XGBoost JSON, the forest as arrays), in ``<trainer.default_root_dir>/baselines/``.
"""

from __future__ import annotations

import time
from pathlib import Path

import lightning as L
import numpy as np
from lightning.pytorch.callbacks import Callback

from datamodules.features import FeatureSchema
from datamodules.graphs import MeshGraphDataModule
from datamodules.trajectories import Breast
from mammo_net import baselines
from mammo_net.inference import breast_prediction
from mammo_net.metrics import breast_rmse, summarize_breasts
from mammo_net.sequence_trees import TreeEnsemble, from_forest, from_xgboost, sequence_predictor


class TreeBaseline(Callback):
    """Common part: fit on the training rows, evaluate per breast, log, save."""

    name = "tree"
    suffix = ".npz"

    def __init__(self, **params: float | int | None) -> None:
        self.params = params
        self.model = None
        self._predictor = None
        self.results: dict[str, float] = {}

    def fit(self, X: np.ndarray, Y: np.ndarray):
        raise NotImplementedError

    def predict(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def save(self, path: Path, schema: FeatureSchema) -> Path:
        raise NotImplementedError

    def ensemble(self) -> TreeEnsemble:
        raise NotImplementedError

    def predictor(self):
        """``(N, T, F) -> (N, T, 3)``: whole sequences through the trees (`sequence_trees`),
        row by row where the features do not separate; built once per fitted model."""
        if self._predictor is None:
            self._predictor = sequence_predictor(self.ensemble(), self.predict)
        return self._predictor

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        dm = trainer.datamodule
        if isinstance(dm, MeshGraphDataModule):
            raise ValueError(
                f"callbacks.{self.name}: the tree baselines train on node rows (data=default), "
                "not on whole-breast graphs (data=graphs); set callbacks=model_checkpoint"
            )
        X, Y = baselines.stack_rows(dm.rows(dm.train))
        t0 = time.perf_counter()
        self.model, self._predictor = self.fit(X, Y), None
        self.results[f"{self.name}/fit_seconds"] = time.perf_counter() - t0
        folder = Path(trainer.default_root_dir) / "baselines"
        self.path = self.save(folder / f"{self.name}{self.suffix}", dm.schema())

    def evaluate(self, breasts: list[Breast]) -> dict[str, float]:
        """Mean / median / std over ``breasts`` of the per-breast RMSE (all steps, last), mm."""
        predict = self.predictor()
        return summarize_breasts(
            [
                breast_rmse(breast_prediction(predict, b), b.normalization().invert(b.targets()))
                for b in breasts
            ]
        )

    def _log(self, trainer: L.Trainer, stage: str) -> None:
        dm = trainer.datamodule
        metrics = {f"{stage}/rmse_{k}_mm/{self.name}": v for k, v in self.evaluate(dm.val).items()}
        self.results.update(metrics)
        if trainer.logger is not None:
            trainer.logger.log_metrics(metrics, step=trainer.global_step)

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._log(trainer, "val")

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._log(trainer, "test")


class XGBoostBaseline(TreeBaseline):
    """XGBoost (`mammo_net.baselines.fit_xgboost`; keyword arguments are its parameters)."""

    name, suffix = "xgboost", ".json"

    def fit(self, X, Y):
        return baselines.fit_xgboost(X, Y, **self.params)

    def predict(self, X):
        return baselines.predict_xgboost(self.model, X)

    def save(self, path, schema):
        return baselines.save_xgboost(self.model, path, schema)

    def ensemble(self):
        return from_xgboost(self.model)


class ERTBaseline(TreeBaseline):
    """Extremely randomized trees (`mammo_net.baselines.fit_ert`)."""

    name, suffix = "ert", ".npz"

    def fit(self, X, Y):
        forest = baselines.fit_ert(X, Y, **self.params)
        self.compiled = forest.compiled(X.shape[1])  # scikit-learn's traversal, same values
        return forest

    def predict(self, X):
        return self.compiled(X)

    def save(self, path, schema):
        return baselines.save_forest(self.model, path, schema)

    def ensemble(self):
        return from_forest(self.model)
