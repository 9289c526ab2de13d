"""train.py end to end on tiny trajectories, and every experiment config instantiated."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import train

CONF = str(Path(__file__).resolve().parents[1] / "conf")


def _cfg(*overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("train", overrides=list(overrides))


def test_train_prints_the_comparison(trajectory_folder, tmp_path, capsys):
    cfg = _cfg(
        f"run_dir={tmp_path}",
        f"cohort.out_dir={trajectory_folder.parent}",
        f"data.data_dir={trajectory_folder}",
        "data.val_fraction=0.25",
        "data.batch_size=16",
        "model.hidden=8",
        "model.layers=1",
        "trainer.max_epochs=2",
        "callbacks.xgboost.n_estimators=5",
        "callbacks.ert.n_estimators=3",
        "callbacks.ert.max_samples=null",
        "callbacks.ert.max_depth=null",
    )
    score = train.train(cfg)
    assert score > 0
    table = (tmp_path / "results.md").read_text()
    for model in ("xgboost", "ert", "att_blstm"):
        assert f"| {model} | (" in table
    assert "| model (test) |" in capsys.readouterr().out
    assert (tmp_path / "baselines" / "xgboost.json").exists()
    assert (tmp_path / "baselines" / "ert.npz").exists()
    assert list((tmp_path / "checkpoints").glob("*.ckpt"))
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))


@pytest.mark.parametrize("experiment", ["paper_compression", "paper_unloaded"])
def test_experiment_configs_instantiate(experiment, tmp_path):
    cfg = _cfg(f"experiment={experiment}", f"run_dir={tmp_path}")
    dm = instantiate(cfg.data)
    assert dm.hparams.step in experiment
    model = instantiate(cfg.model)
    assert model.hparams.n_features == (22 if "compression" in experiment else 11)
    callbacks = {k: instantiate(v) for k, v in cfg.callbacks.items()}
    assert set(callbacks) == {"model_checkpoint", "xgboost", "ert"}
    assert instantiate(cfg.trainer, logger=False).max_epochs == 30
    assert cfg.cohort.n_patients == 258
