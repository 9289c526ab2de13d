"""The prediction API: models load with their schema, and predict_breast builds the same
features as the training caches, batched over thicknesses."""

import csv
from dataclasses import replace
from pathlib import Path

import lightning as L
import meshio
import numpy as np
import pytest
import torch
from conftest import tiny_trajectory
from hydra import compose, initialize_config_dir

import predict
from datamodules.features import FeatureSchema, compression_features, unloaded_features
from datamodules.graphs import PAPER_CONDITIONS, Conditions
from datamodules.trajectories import TrajectoryDataModule
from fem.breasts.io import write_mesh
from fem.contract.trajectory import NodeFlag
from fem.engine.boundary import plate_schedule
from mammo_net import baselines
from mammo_net.module import SurrogateModule
from mammo_net.predictor import RUN_MODELS, load_surrogate, predict_breast

ROOT = Path(__file__).resolve().parents[1]


COMMITTED_MODELS = sorted(  # results/<cv folder>/<model>/<step>/fold<k>/<model file>
    path.relative_to(ROOT / "results")
    for name in RUN_MODELS.values()
    for path in (ROOT / "results").glob(f"cv*/*/*/fold*/{name}")
) + sorted(  # results/resolution/<run>/<step>/checkpoints/best.ckpt: the fine-tuned graph models
    path.relative_to(ROOT / "results")
    for path in (ROOT / "results").glob("resolution/*/*/checkpoints/best.ckpt")
)


@pytest.mark.parametrize("path", COMMITTED_MODELS, ids=str)
def test_committed_models_predict(path):
    """Every model file in results/cv (the paper cohort's folds), results/cv_v2 (the cohort
    v2's) and results/resolution (fine-tuned on remeshed breasts) loads for prediction with this code's inputs: a model
    trained on this code's inputs but saved without their revisions (the graph model's
    compression folds 0-2 until 2026-12-05), or trained before a redefinition of its inputs
    (the Att-BLSTM's compression folds until 2026-12-06), fails here instead of in the report."""
    surrogate = load_surrogate(ROOT / "results" / path)
    assert surrogate.schema.step == path.parts[2]


def scheduled_trajectory(thickness=0.7, patient=0):
    """The tiny trajectory with its plates where the FE puts them for ``thickness``."""
    t = tiny_trajectory("R", patient=patient, site="AB"[patient % 2])
    flags = t.node_flags.copy()
    flags[4] |= NodeFlag.MUSCLE_INTERFACE
    t = replace(t, node_flags=flags)
    plates, ratio = plate_schedule(t, t.unloaded[-1], thickness).recorded(len(t.compressed))
    return replace(t, plates=plates, compression_ratio=ratio)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A tiny network (unloaded state) and XGBoost (compression), saved with their schemas."""
    folder = tmp_path_factory.mktemp("models")
    data = folder / "trajectories"
    data.mkdir()
    for p in range(8):
        scheduled_trajectory(0.6 + 0.02 * p, p).save(data / f"P{p:04d}_R.npz")
    dm = TrajectoryDataModule(str(data), step="unloaded", batch_size=8, val_fraction=0.25)
    dm.prepare_data()
    dm.setup()
    torch.manual_seed(0)
    net = SurrogateModule("unloaded", hidden=4, layers=1)
    net.set_feature_normalization(*dm.feature_statistics(), dm.schema())
    trainer = L.Trainer(max_epochs=1, accelerator="cpu", logger=False, enable_progress_bar=False,
                        enable_checkpointing=False, default_root_dir=folder)  # fmt: skip
    trainer.fit(net, dm)
    trainer.save_checkpoint(folder / "unloaded.ckpt")
    cdm = TrajectoryDataModule(str(data), step="compression", val_fraction=0.25)
    cdm.prepare_data()
    cdm.setup()
    X, Y = baselines.stack_rows(cdm.rows(cdm.train))
    booster = baselines.fit_xgboost(X, Y, n_estimators=5, max_depth=3, n_jobs=1)
    baselines.save_xgboost(booster, folder / "compression.json", cdm.schema())
    baselines.save_xgboost(booster, folder / "no_schema.json")
    return folder


def test_predictions_use_the_training_features(models):
    unloaded = load_surrogate(models / "unloaded.ckpt", "unloaded")
    compression = load_surrogate(models / "compression.json", "compression")
    assert unloaded.schema == FeatureSchema.of("unloaded", 2)
    assert compression.schema == FeatureSchema.of("compression", 3)
    traj = scheduled_trajectory(0.7)
    # With the FE unloaded shape, the compression features are the cached ones exactly.
    fe = predict_breast(traj, None, compression, [0.7])
    features, _, norm = compression_features(traj)
    expected = norm.invert(compression.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    np.testing.assert_allclose(fe.compressed[0], expected, atol=1e-5)
    np.testing.assert_allclose(fe.compression_ratio[0], traj.compression_ratio)
    # The unloaded-state model's steps, then several thicknesses in one batched call.
    shapes = predict_breast(traj, unloaded, compression, [0.5, 0.7, 0.9])
    features, _, norm = unloaded_features(traj)
    expected = norm.invert(unloaded.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    np.testing.assert_allclose(shapes.unloaded, expected, atol=1e-5)
    assert shapes.compressed.shape == (3, 3, 5, 3) and shapes.plates.shape == (3, 3, 2, 3, 3)
    one = predict_breast(traj, unloaded, compression, [0.9])
    np.testing.assert_allclose(shapes.compressed[2], one.compressed[0], atol=1e-5)
    assert shapes.compression_ratio[:, -1].argsort().tolist() == [2, 1, 0]  # thinner: more


def test_wrong_models_and_thicknesses_are_refused(models):
    with pytest.raises(ValueError, match="predicts the unloaded step, not the compression step"):
        load_surrogate(models / "unloaded.ckpt", "compression")
    with pytest.raises(ValueError, match=r"no_schema.json: the file has no feature schema"):
        load_surrogate(models / "no_schema.json")
    with pytest.raises(ValueError, match="a model file ends in one of"):
        load_surrogate(models / "model.pkl")
    unloaded = load_surrogate(models / "unloaded.ckpt")
    compression = load_surrogate(models / "compression.json")
    with pytest.raises(
        ValueError, match="compression model att_blstm: the model predicts the unloaded"
    ):
        predict_breast(scheduled_trajectory(), unloaded, unloaded, [0.7])
    with pytest.raises(ValueError, match="is not smaller than the breast's cranio-caudal extent"):
        predict_breast(scheduled_trajectory(), None, compression, [5.0])
    soft = Conditions({**PAPER_CONDITIONS.young, "fat": 500.0}, 0.25, "cc")
    with pytest.raises(
        ValueError,
        match=r"paper's conditions only \(fat 1100 Pa, gland 2500 Pa, muscle 6000 Pa, skin 1000 "
        r"Pa, friction 0.25, cc\); other stiffness",
    ):
        predict_breast(scheduled_trajectory(), None, compression, [0.7], soft)


def _predict_cfg(models, tmp_path, *overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(
            "predict",
            overrides=[
                f"unloaded_model={models / 'unloaded.ckpt'}",
                f"compression_model={models / 'compression.json'}",
                f"out_dir={tmp_path / 'out'}",
                *overrides,
            ],
        )


def test_predict_writes_meshes_time_series_preview_and_landmarks(models, tmp_path):
    traj = scheduled_trajectory(0.7)
    traj.metadata.pop("laterality")
    meshio_file = tmp_path / "case.vtu"
    write_mesh(traj, meshio_file)  # a user's mesh: no laterality in it
    centroid = traj.points[traj.cells[0]].mean(0)
    (tmp_path / "lm.csv").write_text(
        f"name,x,y,z\nlesion,{centroid[0]},{centroid[1]},{centroid[2]}\n"
    )
    cfg = _predict_cfg(
        models, tmp_path, f"input={meshio_file}", "thickness=[0.6,0.8]", "laterality=R",
        f"landmarks={tmp_path / 'lm.csv'}", "reader.extent_mm=[1,500]",  # a 3 mm test breast
        "projection=raw",  # the raw predictions, to compare with predict_breast's
    )  # fmt: skip
    out = predict.predict(cfg)
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "checks.json", "compressed_0.6mm.vtu", "compressed_0.8mm.vtu", "landmarks.csv", "preview_0.6mm.png",
        "preview_0.8mm.png", "trajectory_0.6mm.xdmf", "trajectory_0.8mm.xdmf", "unloaded.vtu",
    ]  # fmt: skip
    shapes = predict_breast(
        replace(traj, metadata={"laterality": "R"}),
        load_surrogate(models / "unloaded.ckpt"),
        load_surrogate(models / "compression.json"),
        [0.6, 0.8],
    )
    final = meshio.read(out / "compressed_0.8mm.vtu")
    np.testing.assert_allclose(final.points, shapes.compressed[1, -1], atol=1e-5)
    np.testing.assert_array_equal(final.cell_data["tissue"][0], traj.tissue)
    with open(out / "landmarks.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["thickness_mm"] for r in rows] == ["0.600", "0.800"]
    # The landmark is the first element's centroid: it moves with its four nodes.
    expected = shapes.compressed[1, -1][traj.cells[0]].mean(0)
    got = [float(rows[1][f"compressed_{c}"]) for c in "xyz"]
    np.testing.assert_allclose(got, expected, atol=2e-3)


def test_predict_refuses_bad_requests(models, tmp_path):
    traj = scheduled_trajectory(0.7)
    traj.save(tmp_path / "case.npz")
    base = (f"input={tmp_path / 'case.npz'}",)
    with pytest.raises(ValueError, match="is not smaller than the breast's cranio-caudal extent"):
        predict.predict(_predict_cfg(models, tmp_path, *base, "thickness=3"))
    (tmp_path / "empty.csv").write_text("name,x,y,z\n")
    with pytest.raises(ValueError, match=r"empty.csv: no landmarks"):
        predict.predict(
            _predict_cfg(
                models, tmp_path, *base, "thickness=0.7", f"landmarks={tmp_path / 'empty.csv'}"
            )
        )
    (tmp_path / "far.csv").write_text("x,y,z\n100,100,100\n")
    with pytest.raises(
        ValueError, match=r"far.csv: landmark '1' at \[100.0, 100.0, 100.0\] mm lies outside"
    ):
        predict.predict(
            _predict_cfg(
                models, tmp_path, *base, "thickness=0.7", f"landmarks={tmp_path / 'far.csv'}"
            )
        )
    with pytest.raises(ValueError, match="predicts the unloaded step, not the compression step"):
        predict.predict(
            _predict_cfg(
                models,
                tmp_path,
                *base,
                "thickness=0.7",
                f"compression_model={models / 'unloaded.ckpt'}",
            )
        )
    traj.metadata.pop("laterality")
    traj.save(tmp_path / "nolat.npz")
    with pytest.raises(ValueError, match="metadata field 'laterality' must be 'L' or 'R'"):
        predict.predict(
            _predict_cfg(models, tmp_path, f"input={tmp_path / 'nolat.npz'}", "thickness=0.7")
        )


def test_network_precision(models):
    features = unloaded_features(scheduled_trajectory())[0].transpose(1, 0, 2)
    fp32 = load_surrogate(models / "unloaded.ckpt").predict(features)
    bf16 = load_surrogate(models / "unloaded.ckpt", precision="bf16-mixed").predict(features)
    assert bf16.dtype == np.float32
    np.testing.assert_allclose(bf16, fp32, atol=0.05)  # normalised coordinates, ~1
    with pytest.raises(ValueError, match="precision must be one of"):
        load_surrogate(models / "unloaded.ckpt", precision="16")
