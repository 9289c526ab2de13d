"""Train the surrogates and compare them with the tree baselines in one run.

    python train.py                                   # embedded default: small cohort, minutes
    python train.py experiment=paper_compression      # the paper's run on the 516-breast cohort
    python train.py -m experiment=paper_compression data.fold=0,1,2,3,4,5,6,7,8,9
    python train.py -m experiment=[paper_compression,cv_att_blstm] data.fold=3 ckpt_path=last  # resume

Writes TensorBoard logs, checkpoints, the baselines' model files, the validation breasts'
predictions, ``results.md`` (the side-by-side table, also printed) and the evaluation report
(``report/``, `mammo_net.report`) into the run folder.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import lightning as L
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig

from datamodules.trajectories import data_folders
from fem.cohort import run_cohort
from fem.contract.atomic import atomic_path, writable_folder
from mammo_net.callbacks import TreeBaseline
from mammo_net.inference import save_predictions
from mammo_net.metrics import comparison
from mammo_net.module import NetworkModule  # importing it stores the models' config nodes
from mammo_net.report import write_report


def ensure_cohort(cfg: DictConfig) -> None:
    """Build the configured cohort, or finish a partial build (resumable: finished breasts are
    skipped), when a trajectory folder of ``data.data_dir`` is the cohort's."""
    folders = {Path(to_absolute_path(str(f))) for f in data_folders(cfg.data.data_dir)}
    if Path(to_absolute_path(cfg.cohort.out_dir)) / "trajectories" in folders:
        run_cohort(cfg.cohort)


def resume_from(cfg: DictConfig) -> str | None:
    """The checkpoint an interrupted fit resumes from (``ckpt_path``): ``last`` is the run
    folder's ``checkpoints/last.ckpt`` when it exists (a first run starts from scratch).

    Raises
    ------
    FileNotFoundError
        ``ckpt_path`` names a file that does not exist.
    """
    if cfg.ckpt_path is None:
        return None
    if cfg.ckpt_path == "last":
        last = Path(cfg.run_dir) / "checkpoints" / "last.ckpt"
        return str(last) if last.exists() else None
    path = Path(to_absolute_path(str(cfg.ckpt_path)))
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: {path}: no such checkpoint")
    return str(path)


def logged(trainer: L.Trainer, baselines: list[TreeBaseline]) -> dict[str, float]:
    """Every metric of the run so far: the network's and the baselines'."""
    out = {k: float(v) for k, v in trainer.callback_metrics.items()}
    for c in baselines:
        out.update(c.results)
    return out


def train(cfg: DictConfig) -> float:
    """Fit (and test) on a composed config; returns the validation metric ``optimized_metric``.

    The run folder, the data and the model settings are checked before the cohort is built,
    the features cached or anything written. The data folders are opened relative to the
    folder train.py starts in (``hydra.job.chdir`` is false) and recorded as written."""
    writable_folder(cfg.run_dir)
    resume = resume_from(cfg)
    L.seed_everything(cfg.seed, workers=True)
    dm = instantiate(cfg.data)
    model: NetworkModule = instantiate(cfg.model)
    model.check_data_step(dm.hparams.step)
    ensure_cohort(cfg)
    dm.prepare_data()
    dm.setup()
    model.adapt(dm)
    if cfg.get("init_from"):
        model.start_from(to_absolute_path(str(cfg.init_from)))
    # entries without _target_: a paper experiment's parameters of a callback left out
    callbacks = [instantiate(c) for c in cfg.callbacks.values() if c and "_target_" in c]
    baselines = [c for c in callbacks if isinstance(c, TreeBaseline)]
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=logger)
    start = time.perf_counter()
    trainer.fit(model, dm, ckpt_path=resume, weights_only=True)
    network = (
        time.perf_counter() - start - sum(c.results[f"{c.name}/fit_seconds"] for c in baselines)
    )
    # the kept checkpoint's weights (the best epoch's, when a checkpoint callback monitors
    # one) are the model of the score, the table and the predictions
    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    if best:
        trainer.validate(model, dm, ckpt_path=best, weights_only=True, verbose=False)
    metrics = logged(trainer, baselines)
    if cfg.optimized_metric not in metrics:
        raise KeyError(
            f"optimized_metric {cfg.optimized_metric!r} was not logged: {sorted(metrics)}"
        )
    score = metrics[cfg.optimized_metric]
    stage = "test" if cfg.test else "val"
    if cfg.test:
        trainer.test(model, dm, weights_only=True)
        metrics = logged(trainer, baselines)
    trained = trainer.global_step > 0  # False for baseline-only runs (trainer.max_epochs=0)
    if trained:
        metrics[f"{model.name} ({trainer.current_epoch} epochs)/fit_seconds"] = network
    table = comparison(metrics, stage, model.name)
    if trainer.is_global_zero:  # the validation breasts' predictions, mm, for the report
        folder = Path(cfg.run_dir) / "predictions"
        if trained:
            save_predictions(folder / f"{model.name}.npz", model.predictor(), dm.val)
        for c in baselines:
            save_predictions(folder / f"{c.name}.npz", c.predictor(), dm.val)
        with atomic_path(Path(cfg.run_dir) / "results.md") as tmp:
            tmp.write_text(table)
        print(table)
        if cfg.report:  # tables and figures of this run: python -m mammo_net.report on it
            projection = instantiate(cfg.projection) if cfg.get("projection") else None
            out = Path(cfg.run_dir) / "report"
            print("report:", write_report([cfg.run_dir], out, cfg.analysis, projection=projection))
    return score


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float:
    return train(cfg)


if __name__ == "__main__":
    main()
