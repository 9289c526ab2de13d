"""train.py end to end on tiny trajectories, and every experiment config instantiated."""

import json
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import train
from datamodules.features import FeatureSchema
from datamodules.graphs import MeshGraphDataModule
from datamodules.trajectories import TrajectoryDataModule
from fem.contract.trajectory import Trajectory
from mammo_net.baselines import forest_schema, load_xgboost, xgboost_schema
from mammo_net.inference import load_predictions, save_predictions
from mammo_net.metrics import breast_rmse, comparison
from mammo_net.models import PAPER_ACTIVATIONS
from mammo_net.module import NetworkModule, SurrogateModule, signature_defaults
from mammo_net.report import write_report

ROOT = Path(__file__).resolve().parents[1]
CONF = str(ROOT / "conf")


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
        "report=false",  # needs the .hydra folder of a command-line run (the tests below)
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
    schema = FeatureSchema.of("compression", 3)  # every model file knows what it takes
    assert xgboost_schema(load_xgboost(tmp_path / "baselines" / "xgboost.json")) == schema
    assert forest_schema(tmp_path / "baselines" / "ert.npz") == schema
    ckpt = next((tmp_path / "checkpoints").glob("*.ckpt"))
    assert SurrogateModule.from_checkpoint(ckpt).schema == schema
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    # The saved predictions (mm) reproduce the table's test errors against the FE positions.
    for model in ("xgboost", "ert", "att_blstm"):
        predictions = load_predictions(tmp_path / "predictions" / f"{model}.npz")
        assert len(predictions) == 6  # the validation breasts
        errors = [
            breast_rmse(
                p, Trajectory.load(trajectory_folder / f"{name}.npz").compressed.transpose(1, 0, 2)
            )
            for name, p in predictions.items()
        ]
        mean = sum(e["last_step"] for e in errors) / len(errors)
        row = next(line for line in table.splitlines() if line.startswith(f"| {model} |"))
        assert row.split("| (")[2].startswith(f"{mean:.2f},")  # last step: (mean, ...


def test_train_composes_the_cohort_settings():
    """train.py's cohort is conf/cohort.yaml's, smaller and in its own folder; cohort.yaml's
    hydra settings stay its own."""
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cohort = compose("cohort", return_hydra_config=True)
        trained = compose("train", overrides=["cohort.workers=3"], return_hydra_config=True)
    expected = OmegaConf.to_container(cohort)
    del expected["hydra"]
    expected.update(n_patients=6, out_dir="data/cohort/train_default", figures=False, workers=3)
    assert OmegaConf.to_container(trained.cohort) == expected
    assert cohort.hydra.run.dir.startswith("data/cohort/default/hydra/")
    assert trained.hydra.run.dir.startswith("outputs/train/")


def test_model_settings_are_the_module_signature():
    """The model's keys are SurrogateModule's arguments with their defaults, overridden without
    ``+``; its step is the data's."""
    cfg = _cfg("data.step=unloaded", "model.hidden=16")
    settings = {k: v for k, v in cfg.model.items() if k not in ("_target_", "step")}
    assert settings == {**signature_defaults(SurrogateModule), "hidden": 16}
    model = instantiate(cfg.model)
    assert model.hparams.step == "unloaded" and model.n_features == 11
    assert model.hparams.activations == PAPER_ACTIVATIONS["unloaded"]
    assert model.hparams.hidden == 16


def test_data_folders_and_condition_bounds_from_the_command_line(monkeypatch, tmp_path):
    """``data.data_dir=[...]`` and ``data.train_conditions={...}`` (docs/cohort.md's cohort v2
    command) compose and instantiate; the folders are recorded as written; the cohort is built
    when one of them is its trajectory folder."""
    monkeypatch.chdir(tmp_path)
    cfg = _cfg(
        "experiment=[paper_compression,mesh_gnn,cv_mesh_gnn]",
        "data.data_dir=[data/cohort/v2/trajectories,data/cohort/v2/trajectories_mlo]",
        "data.train_conditions={young_fat:[700,2600],young_gland:[1600,5900]}",
        "data.fold=0",
    )
    dm = instantiate(cfg.data)
    assert isinstance(dm, MeshGraphDataModule)
    assert dm.hparams.data_dir == ["data/cohort/v2/trajectories", "data/cohort/v2/trajectories_mlo"]
    assert dm.data_dirs[1] == tmp_path / "data/cohort/v2/trajectories_mlo"
    assert dm.bounds == {"young_fat": (700.0, 2600.0), "young_gland": (1600.0, 5900.0)}
    built = []
    monkeypatch.setattr(train, "run_cohort", built.append)
    train.ensure_cohort(cfg)  # the cohort is data/cohort/full: not one of the folders
    assert not built
    cohort = "cohort.out_dir=data/cohort/v2"
    train.ensure_cohort(_cfg(cohort, "data.data_dir=[elsewhere/x,data/cohort/v2/trajectories]"))
    assert len(built) == 1


def test_train_refuses_a_model_of_another_step(tmp_path):
    cfg = _cfg(
        f"run_dir={tmp_path}",
        f"data.data_dir={tmp_path / 'absent'}",  # refused before the data are read
        "data.step=unloaded",
        "model.step=compression",
    )
    with pytest.raises(ValueError, match=r"model\.step=compression .*data\.step=unloaded"):
        train.train(cfg)


@pytest.mark.parametrize("experiment", ["paper_compression", "paper_unloaded"])
def test_experiment_configs_instantiate(experiment, tmp_path):
    cfg = _cfg(f"experiment={experiment}", f"run_dir={tmp_path}")
    dm = instantiate(cfg.data)
    assert dm.hparams.step in experiment
    model = instantiate(cfg.model)
    assert model.n_features == (22 if "compression" in experiment else 11)
    assert model.hparams.activations == PAPER_ACTIVATIONS[dm.hparams.step]
    callbacks = {k: instantiate(v) for k, v in cfg.callbacks.items()}
    assert set(callbacks) == {"model_checkpoint", "xgboost", "ert"}
    assert instantiate(cfg.trainer, logger=False).max_epochs == 30
    assert cfg.cohort.n_patients == 258


@pytest.mark.parametrize("step", ["compression", "unloaded"])
@pytest.mark.parametrize("cv", ["cv_xgboost", "cv_att_blstm"])
def test_cross_validation_configs_instantiate(step, cv, tmp_path):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[f"experiment=[paper_{step},{cv}]", f"run_dir={tmp_path}", "data.fold=4"],
            return_hydra_config=True,
        )
    assert cfg.hydra.sweeper.params["data.fold"].startswith("range(0, 10)")
    assert cfg.hydra.sweep.dir == f"results/cv/{cv[3:]}/{step}"  # committed model files
    callbacks = [instantiate(c) for c in cfg.callbacks.values() if c and "_target_" in c]
    assert len(callbacks) == (1 if cv == "cv_xgboost" else 2)  # the network's: + resume state
    for c in callbacks:  # a retrained fold replaces its committed best.ckpt, no best-v1.ckpt
        assert getattr(c, "filename", None) != "best" or not c._enable_version_counter
    dm, model = instantiate(cfg.data), instantiate(cfg.model)
    assert dm.hparams.step == step and dm.hparams.fold == 4
    assert model.n_features == (22 if step == "compression" else 11)
    assert cfg.trainer.max_epochs == (0 if cv == "cv_xgboost" else 4)  # the graph model's budget


@pytest.mark.parametrize(
    "search, metric",
    [
        ("att_blstm_optuna", "val/rmse_all_steps_mean_mm"),
        ("xgboost_optuna", "val/rmse_all_steps_mean_mm/xgboost"),
    ],
)
def test_hparams_search_configs_instantiate(search, metric, tmp_path):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[f"hparams_search={search}", f"run_dir={tmp_path}"],
            return_hydra_config=True,
        )
    assert cfg.optimized_metric == metric and cfg.hydra.sweeper.direction == "minimize"
    assert "optuna" in cfg.hydra.sweeper._target_
    for name in cfg.hydra.sweeper.params:  # every searched key exists in the run's config
        assert OmegaConf.select(cfg, name) is not None, name
    instantiate(cfg.model), instantiate(cfg.data)
    assert {k: instantiate(v) for k, v in cfg.callbacks.items()}


TINY = (
    "data.val_fraction=0.25",
    "data.batch_size=4",
    "model.hidden=4",
    "model.layers=1",
    "~logger",
    "+trainer.enable_progress_bar=false",
)


def test_train_the_unloaded_step(trajectory_folder, tmp_path):
    """``python train.py data.step=unloaded``: the network takes the step's 11 features."""
    cfg = _cfg(
        f"run_dir={tmp_path}",
        f"data.data_dir={trajectory_folder}",
        "data.step=unloaded",
        "trainer.max_epochs=1",
        "callbacks=model_checkpoint",
        "report=false",
        *TINY,
    )
    assert train.train(cfg) > 0
    assert "| att_blstm | (" in (tmp_path / "results.md").read_text()
    model = SurrogateModule.from_checkpoint(tmp_path / "checkpoints" / "last.ckpt")
    assert model.schema == FeatureSchema.of("unloaded", 2)  # tiny trajectories: 2 steps
    assert model.hparams.activations == PAPER_ACTIVATIONS["unloaded"]


@pytest.mark.parametrize(
    "callbacks",
    [
        ("callbacks=model_checkpoint",),
        ("experiment=[paper_compression,cv_att_blstm]", "data.fold=0"),
    ],
    ids=["model_checkpoint", "cross_validation_fold"],
)
def test_an_interrupted_fit_resumes_from_the_last_checkpoint(
    trajectory_folder, tmp_path, monkeypatch, callbacks
):
    """``ckpt_path=last``: a fold folder's fit goes on from its checkpoints/last.ckpt (the
    optimizer, the schedule and the epoch counter with it); a first run starts from scratch.
    Also with a cross-validation fold's callbacks (weights-only best.ckpt and the resume
    state), whose last.ckpt Lightning 2.6 skipped while the resume callback saved no top-k."""
    steps = []
    training_step = NetworkModule.training_step
    monkeypatch.setattr(
        NetworkModule, "training_step", lambda self, *a: steps.append(1) or training_step(self, *a)
    )
    common = (
        f"run_dir={tmp_path}",
        f"data.data_dir={trajectory_folder}",
        *callbacks,
        "test=false",
        "report=false",
        *TINY,
    )
    last = tmp_path / "checkpoints" / "last.ckpt"
    train.train(_cfg(*common, "ckpt_path=last", "trainer.max_epochs=1"))  # none yet: from scratch
    first = torch.load(last, weights_only=True)
    assert first["epoch"] == 0 and first["global_step"] > 0
    assert len(steps) == first["global_step"]
    train.train(_cfg(*common, "ckpt_path=last", "trainer.max_epochs=2"))
    resumed = torch.load(last, weights_only=True)
    assert resumed["epoch"] == 1 and resumed["global_step"] == 2 * first["global_step"]
    assert len(steps) == 2 * first["global_step"]  # one more epoch, not two from scratch
    with pytest.raises(FileNotFoundError, match=r"ckpt_path: .*nowhere\.ckpt: no such checkpoint"):
        train.train(_cfg(*common, f"ckpt_path={tmp_path / 'nowhere.ckpt'}"))


def _run_train(tmp_path, trajectory_folder, *overrides, multirun=False):
    """``python train.py`` in a subprocess on the tiny trajectories; returns its stdout."""
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            *(["-m"] if multirun else []),
            f"data.data_dir={trajectory_folder}",
            *TINY,
            *overrides,
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_xgboost_optuna_sweep_runs(trajectory_folder, tmp_path):
    out = tmp_path / "sweep"
    _run_train(
        tmp_path,
        trajectory_folder,
        "hparams_search=xgboost_optuna",
        "hydra.sweeper.n_trials=2",
        "hydra.sweeper.sampler.n_startup_trials=1",
        f"hydra.sweep.dir={out}",
        multirun=True,
    )
    result = OmegaConf.load(out / "optimization_results.yaml")
    assert result.best_value > 0
    assert set(result.best_params) == {
        "callbacks.xgboost.n_estimators",
        "callbacks.xgboost.learning_rate",
        "callbacks.xgboost.max_depth",
        "callbacks.xgboost.min_child_weight",
    }


def test_two_process_cpu_ddp(trajectory_folder, tmp_path):
    """Two CPU processes with DDP: the gathered validation errors equal one process's."""
    run = tmp_path / "ddp"
    _run_train(
        tmp_path,
        trajectory_folder,
        "trainer=ddp_cpu",
        "trainer.max_epochs=1",
        "callbacks=model_checkpoint",
        f"hydra.run.dir={run}",
    )
    logged = (run / "results.md").read_text()
    report = (run / "report" / "report.md").read_text()  # the run's own evaluation report
    assert "| one-fold | compression | att_blstm | 6 | (" in report
    assert "after the validity projection" in report  # scored as predict.py writes them
    assert (run / "report" / "figures" / "one_fold_compression_sections_worst.png").exists()
    model = SurrogateModule.from_checkpoint(next((run / "checkpoints").glob("epoch*.ckpt")))
    dm = TrajectoryDataModule(str(trajectory_folder), val_fraction=0.25, batch_size=5)
    dm.setup()
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False)
    single = trainer.test(model, dm, verbose=False)[0]
    expected = comparison(single, "test").splitlines()[2]
    assert expected in logged.splitlines()


def test_cross_validation_sweeps_feed_the_report(trajectory_folder, tmp_path):
    """Two folds of each model's cross-validation, then one report over both models."""
    for cv in ("cv_xgboost", "cv_att_blstm"):
        _run_train(
            tmp_path,
            trajectory_folder,
            f"experiment=[paper_compression,{cv}]",
            "data.fold=0,1",
            "callbacks.xgboost.n_estimators=3",
            *(["trainer.max_epochs=1"] if cv == "cv_att_blstm" else []),  # cv_xgboost's: 0
            multirun=True,
        )
    folds = sorted(p.relative_to(tmp_path) for p in tmp_path.glob("*/cv/*/*/fold*"))
    assert [str(p) for p in folds] == [
        "results/cv/att_blstm/compression/fold0",
        "results/cv/att_blstm/compression/fold1",
        "results/cv/xgboost/compression/fold0",
        "results/cv/xgboost/compression/fold1",
    ]
    # A fold kept as committed files (model files, no predictions) is predicted again.
    fold0 = tmp_path / "results/cv/att_blstm/compression/fold0"
    assert sorted(p.name for p in (fold0 / "checkpoints").iterdir()) == ["best.ckpt", "last.ckpt"]
    assert "optimizer_states" not in torch.load(fold0 / "checkpoints/best.ckpt", weights_only=True)
    # last.ckpt (gitignored) is the fold's resume state: ckpt_path=last
    assert "optimizer_states" in torch.load(fold0 / "checkpoints/last.ckpt", weights_only=True)
    kept = {
        model: tmp_path / f"results/cv/{model}/compression/fold0/predictions/{model}.npz"
        for model in ("att_blstm", "xgboost")
    }
    saved = {model: load_predictions(path) for model, path in kept.items()}
    timings = {model: path.with_suffix(".json").read_bytes() for model, path in kept.items()}
    for path in kept.values():
        path.unlink()
    analysis = OmegaConf.load(CONF + "/analysis/default.yaml")
    out = write_report([tmp_path / "results/cv/*/*/fold*"], tmp_path / "report", analysis)
    for model, path in kept.items():
        again = load_predictions(path)
        assert saved[model].keys() == again.keys()
        for name in again:
            np.testing.assert_allclose(again[name], saved[model][name], atol=1e-4)  # mm
        assert path.with_suffix(".json").read_bytes() == timings[model]  # the run's own timing
    summary = json.loads((out / "report.json").read_text())["summary"]
    # 24 breasts, 10 folds: folds 0 and 1 validate 2 patients (4 breasts) each -> 8 breasts.
    for model in ("att_blstm", "xgboost"):
        assert summary["10_fold_CV_compression"][model]["n_breasts"] == 8


@pytest.mark.parametrize("step", ["compression", "unloaded"])
@pytest.mark.parametrize("cv", [None, "cv_mesh_gnn"])
def test_graph_model_configs_instantiate(step, cv, tmp_path):
    experiments = ",".join(e for e in (f"paper_{step}", "mesh_gnn", cv) if e)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[f"experiment=[{experiments}]", f"run_dir={tmp_path}", "data.fold=4"],
            return_hydra_config=True,
        )
    if cv:
        assert cfg.hydra.sweep.dir == f"results/cv/mesh_gnn/{step}"
        assert cfg.hydra.sweeper.params["data.fold"].startswith("range(0, 10)")
    dm, model = instantiate(cfg.data), instantiate(cfg.model)
    assert type(dm).__name__ == "MeshGraphDataModule" and dm.hparams.step == step
    assert model.name == "mesh_gnn" and model.hparams.step == step
    settings = {k: v for k, v in cfg.model.items() if k not in ("_target_", "step")}
    assert set(settings) == set(signature_defaults(type(model)))
    callbacks = [instantiate(c) for c in cfg.callbacks.values() if c and "_target_" in c]
    assert [type(c).__name__ for c in callbacks] == ["ModelCheckpoint"] * (2 if cv else 1)
    if cv:  # the model's weights, and the resume state (`ckpt_path=last`)
        best, last = callbacks
        assert best.save_weights_only and best.save_top_k == 1 and not best.save_last
        assert not last.save_weights_only and last.monitor is None and last.filename == "last"


@pytest.mark.parametrize("trainer", [(), ("trainer=gpu", "trainer.accelerator=cpu")])
def test_train_the_graph_model(trajectory_folder, tmp_path, trainer):
    """``python train.py experiment=mesh_gnn``: the graph model's table row and the validation
    breasts' predictions in millimetres, as the Att-BLSTM's; also with the GPU path's trainer
    (bfloat16 autocast, here on the CPU)."""
    cfg = _cfg(
        "experiment=mesh_gnn",
        *trainer,
        f"run_dir={tmp_path}",
        f"data.data_dir={trajectory_folder}",
        "data.val_fraction=0.25",
        "model.hidden=8",
        "model.layers=1",
        "model.slices=2",
        "model.heads=1",
        "model.decoder_hidden=8",
        "trainer.max_epochs=2",
        "model.lr=0.01",
        "callbacks.model_checkpoint.mode=max",  # keeps the worse epoch: the first one
        "test=false",  # as the cross-validation folds: the table of the validation breasts
        "~logger",
        "+trainer.enable_progress_bar=false",
        "report=false",
    )
    assert train.train(cfg) > 0
    table = (tmp_path / "results.md").read_text()
    assert "| mesh_gnn | (" in table and "mesh_gnn (2 epochs)" in table
    predictions = load_predictions(tmp_path / "predictions" / "mesh_gnn.npz")
    assert len(predictions) == 6
    for name, p in predictions.items():
        truth = Trajectory.load(trajectory_folder / f"{name}.npz").compressed.transpose(1, 0, 2)
        assert p.shape == truth.shape and np.isfinite(p).all()
    # the predictions are the kept checkpoint's (the best epoch's), not the last epoch's
    best = tmp_path / "checkpoints" / "best.ckpt"
    assert torch.load(best, weights_only=True)["epoch"] == 0
    kept = NetworkModule.from_checkpoint(best)
    dm = MeshGraphDataModule(str(trajectory_folder), "compression", val_fraction=0.25)
    dm.prepare_data()
    dm.setup()
    again = load_predictions(save_predictions(tmp_path / "again.npz", kept.predictor(), dm.val))
    for name, p in predictions.items():
        np.testing.assert_allclose(again[name], p, atol=1e-4)
