"""Train the surrogates and compare them with the tree baselines in one run.

    python train.py                                   # embedded default: small cohort, minutes
    python train.py experiment=paper_compression      # the paper's run on the 516-breast cohort
    python train.py -m experiment=paper_compression data.split=k_fold data.fold=0,1,2,3,4,5,6,7,8,9

Writes TensorBoard logs, checkpoints, the baselines' model files and ``results.md`` (the
side-by-side table) into the run folder, and prints the table.
"""

from __future__ import annotations

from pathlib import Path

import hydra
import lightning as L
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig

from fem.atomic import atomic_path
from fem.cohort import run_cohort
from mammo_net.callbacks import TreeBaseline

COLUMNS = ("all_steps", "last_step")


def ensure_cohort(cfg: DictConfig) -> str:
    """The trajectory folder; the configured cohort is generated and simulated if it is empty."""
    data_dir = Path(to_absolute_path(cfg.data.data_dir))
    if not any(data_dir.glob("P*_[LR].npz")):
        run_cohort(cfg.cohort)
    return str(data_dir)


def comparison(rows: dict[str, dict[str, float]], stage: str) -> str:
    """Markdown table: (mean, median) +- std of the per-breast RMSE, mm, per model."""
    lines = [
        f"| model ({stage}) | all steps: (mean, median) +- std | last step: (mean, median) +- std |",
        "| --- | --- | --- |",
    ]
    for model, m in rows.items():
        cells = [
            f"({m[f'{c}_mean']:.2f}, {m[f'{c}_median']:.2f}) +- {m[f'{c}_std']:.2f}"
            if f"{c}_mean" in m
            else "-"
            for c in COLUMNS
        ]
        lines.append(f"| {model} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def train(cfg: DictConfig) -> float:
    """Fit (and test) on a composed config; returns the network's validation RMSE (mm)."""
    L.seed_everything(cfg.seed, workers=True)
    dm = instantiate(cfg.data, data_dir=ensure_cohort(cfg))
    dm.prepare_data()
    dm.setup()
    model = instantiate(cfg.model)
    model.set_feature_normalization(*dm.feature_statistics())
    callbacks = [instantiate(c) for c in cfg.callbacks.values()]
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=logger)
    trainer.fit(model, dm)
    score = float(trainer.callback_metrics["val/rmse_all_steps_mean_mm"])
    stage = "test" if cfg.test else "val"
    if cfg.test:
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        trainer.test(model, dm, ckpt_path=best or None, weights_only=True)
    prefix = f"{stage}/rmse_"
    rows = {
        c.name: {
            k[len(prefix) :].split("_mm/")[0]: v
            for k, v in c.results.items()
            if k.startswith(prefix)
        }
        for c in callbacks
        if isinstance(c, TreeBaseline)
    }
    rows["att_blstm"] = {
        k[len(prefix) : -3]: float(v)
        for k, v in trainer.callback_metrics.items()
        if k.startswith(prefix) and k.endswith("_mm")
    }
    table = comparison(rows, stage)
    if trainer.is_global_zero:
        with atomic_path(Path(cfg.run_dir) / "results.md") as tmp:
            tmp.write_text(table)
        print(table)
    return score


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float:
    return train(cfg)


if __name__ == "__main__":
    main()
