"""Bad input gets one clear error that names the file or the setting, and leaves no output.

The corpus grows per command; docs/reliability.md tabulates it."""

from __future__ import annotations

import functools
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import meshio
import nibabel
import nrrd
import numpy as np
import pytest
import xgboost as xgb
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException
from omegaconf import OmegaConf
from test_cohort import _cfg as _cohort_cfg
from test_predictor import _predict_cfg, models, scheduled_trajectory  # noqa: F401 (fixture)
from test_report import cohort  # noqa: F401 (fixture)

from datamodules.features import FeatureSchema
from datamodules.trajectories import TrajectoryDataModule
from fem.breasts.io import BreastReader
from fem.contract.trajectory import Trajectory
from mammo_net.baselines import fit_ert, fit_xgboost, load_forest, load_xgboost, save_xgboost
from mammo_net.predictor import load_surrogate, read_landmarks
from mammo_net.report import write_report

ROOT = Path(__file__).resolve().parents[1]  # the repository
CONF = str(ROOT / "conf")


def _run_folder(root: Path, data: str) -> Path:
    run = root / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(data)
    (run / "baselines").mkdir()
    (run / "baselines" / "xgboost.json").write_text("{}")  # a model to predict with
    return run


def test_a_crafted_run_folder_executes_nothing(tmp_path):
    """The report reads plain values from a run folder's config; a `_target_` there (here one
    that would create a folder) is never called."""
    sentinel = tmp_path / "executed"
    run = _run_folder(
        tmp_path,
        f"data:\n  _target_: os.mkdir\n  path: {sentinel}\n  data_dir: {tmp_path / 'none'}\n"
        "  step: compression\n",
    )
    with pytest.raises(FileNotFoundError, match="no simulated trajectories"):
        write_report([run], tmp_path / "report", analysis=None)
    assert not sentinel.exists()
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ("data:\n  data_dir: d\n  step: [1]\n", "field 'data.step' must be str, got"),
        ("data:\n  data_dir: d\n  fold: '3'\n", "field 'data.fold' must be int or NoneType"),
        ("data: [\n", "unreadable data settings"),
        ("model: {}\n", "unreadable data settings"),
        ("data:\n  data_dir: ${hydra:runtime.cwd}\n", "unreadable data settings"),
    ],
)
def test_bad_run_folder_settings_name_the_file_and_field(tmp_path, data, message):
    run = _run_folder(tmp_path, data)
    with pytest.raises(ValueError, match=message) as info:
        TrajectoryDataModule.from_run(run)
    assert str(run / ".hydra" / "config.yaml") in str(info.value)


def test_a_folder_without_run_config_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"config.yaml: not found; is .* a train.py run"):
        TrajectoryDataModule.from_run(tmp_path)


def test_an_unwritable_output_folder_is_refused_before_the_fe_run(tmp_path, monkeypatch):
    """fem.simulate checks its output folder before simulating (not after minutes of FE)."""
    from hydra import compose, initialize_config_dir

    from fem import CONFIG_DIR
    from fem.engine import simulation
    from fem.simulate import simulate_file

    blocked = tmp_path / "file"
    blocked.write_text("")  # a file where the output folder should be
    monkeypatch.setattr(simulation.Simulation, "__call__", lambda *_: pytest.fail("simulated"))
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("simulate", [f"input={tmp_path / 'in.vtu'}", f"output={blocked / 'case'}"])
    with pytest.raises(PermissionError, match=r"file: cannot write output files there"):
        simulate_file(cfg)


# --- a user's files: segmentations, meshes, trajectories, model files, landmarks ---------------
#
# Each bad file gets ONE error of exactly the type named (never SystemExit, StopIteration,
# EOFError, BadZipFile, KeyError, nor a library's own ValueError subclass such as
# XGBoostError or JSONDecodeError), whose message names the file and what is wrong with it,
# never suggests unsafe loading, and nothing is written beside the file.


def _nifti(tmp: Path, volume, name: str = "seg.nii.gz") -> Path:
    nibabel.save(nibabel.Nifti1Image(volume.labels, volume.affine), str(tmp / name))
    return tmp / name


def _truncated(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _empty(name: str):
    def make(tmp: Path, volume, mesh) -> Path:
        (tmp / name).write_bytes(b"")
        return tmp / name

    return make


def _bytes(name: str, data: bytes):
    def make(tmp: Path, volume, mesh) -> Path:
        (tmp / name).write_bytes(data)
        return tmp / name

    return make


def _folder(path: Path) -> Path:
    path.mkdir()
    return path


def _npz(name: str, **arrays):
    def make(tmp: Path, volume, mesh) -> Path:
        np.savez(tmp / name, **{k: v(volume) if callable(v) else v for k, v in arrays.items()})
        return tmp / name

    return make


def _vtu(scale: float = 1.0, nan: bool = False, bad_index: bool = False):
    def make(tmp: Path, volume, mesh) -> Path:
        points, cells = mesh.points * scale, mesh.cells.copy()
        if nan:
            points[7, 1] = np.nan
        if bad_index:
            cells[3, 2] = len(points) + 5
        m = meshio.Mesh(points, [("tetra", cells)], cell_data={"tissue": [mesh.tissue]})
        meshio.write(tmp / "breast.vtu", m)
        return tmp / "breast.vtu"

    return make


def _nrrd_header(**header):
    def make(tmp: Path, volume, mesh) -> Path:
        nrrd.write(str(tmp / "seg.nrrd"), volume.labels, header)
        return tmp / "seg.nrrd"

    return make


def _trajectory(**changes):
    """A saved breast with some fields replaced (raw arrays, as a foreign writer would)."""

    def make(tmp: Path, volume, mesh) -> Path:
        with np.load(mesh.save(tmp / "t.npz")) as z:
            arrays = {k: z[k] for k in z.files}
        arrays.update(changes)
        np.savez(tmp / "breast.npz", **arrays)
        (tmp / "t.npz").unlink()
        return tmp / "breast.npz"

    return make


def _xy(n: int = 300, n_out: int = 3):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(n, 5)).astype(np.float32)
    return X, np.repeat(X[:, :1], n_out, axis=1)


def _foreign_xgboost(tmp: Path, volume, mesh) -> Path:
    """A valid XGBoost model, trained by plain xgboost: one output, no feature schema."""
    X, y = _xy(n_out=1)
    xgb.train({"max_depth": 2}, xgb.DMatrix(X, y), 3).save_model(str(tmp / "model.json"))
    return tmp / "model.json"


def _schemaless_xgboost(tmp: Path, volume, mesh) -> Path:
    """Another project's x, y, z tree model: no feature schema."""
    X, Y = _xy()
    return save_xgboost(fit_xgboost(X, Y, n_estimators=2, max_depth=2, n_jobs=1), tmp / "m.json")


def _forest(tmp: Path, change=None, schema: FeatureSchema | None = None) -> Path:
    X, Y = _xy()
    forest = fit_ert(X, Y, n_estimators=2, max_depth=3, n_jobs=1)
    arrays = {k: v for k, v in vars(forest).items()}
    if change:
        change(arrays)
    if schema is not None:
        arrays["feature_schema"] = np.array(schema.to_json())
    np.savez(tmp / "ert.npz", **arrays)
    return tmp / "ert.npz"


def _cycle(arrays: dict) -> None:
    arrays["left"] = arrays["left"].copy()
    arrays["left"][0] = 0  # the root is its own left child: an endless descent


def _far_feature(arrays: dict) -> None:
    arrays["feature"] = np.where(arrays["left"] >= 0, 40, arrays["feature"])


def _reader(path: Path) -> object:
    return BreastReader()(path)


BAD_FILES = [
    # segmentations (BreastReader, as fem.mesh_breast, fem.simulate and predict.py read them)
    (_empty("seg.nrrd"), _reader, ValueError, "the file is empty"),
    (_empty("seg.nii.gz"), _reader, ValueError, "the file is empty"),
    (_empty("seg.npz"), _reader, ValueError, "the file is empty"),
    (lambda t, v, m: _truncated(_nifti(t, v)), _reader, ValueError, "EOFError"),
    (lambda t, v, m: _truncated(_nifti(t, v, "seg.nii")), _reader, ValueError, "truncated"),
    (
        lambda t, v, m: _truncated(_npz("seg.npz", labels=lambda v: v.labels)(t, v, m)),
        _reader,
        ValueError,
        "truncated or corrupt",
    ),
    (_bytes("seg.nrrd", b"NRRD0004\ntype: bogus\n\n"), _reader, ValueError, "corrupt"),
    (_bytes("seg.nii", b"\x89PNG\r\n\x1a\n" + bytes(64)), _reader, ValueError, "a PNG image"),
    (_bytes("seg.npy", b"\x80\x04K\x01."), _reader, ValueError, "it is a Python pickle"),
    (
        _npz("seg.npz", labels=np.array([{}], dtype=object)),
        _reader,
        ValueError,
        "pickled Python objects, which are never loaded",
    ),
    (_npz("seg.npz", voxels=lambda v: v.labels), _reader, ValueError, "field 'labels' is missing"),
    (
        _npz("seg.npz", labels=lambda v: v.labels, spacing=np.zeros(3)),
        _reader,
        ValueError,
        "field 'spacing' must be three finite voxel sizes > 0",
    ),
    (
        _nrrd_header(**{"space": "RAS", "space directions": np.zeros((3, 3))}),
        _reader,
        ValueError,
        "degenerate",
    ),
    (_nrrd_header(space="scanner-xyz"), _reader, ValueError, "reader.orientation"),
    (_npz("seg.npz", labels=np.ones((4, 4))), _reader, ValueError, "must be a 3-D array"),
    (
        _npz("seg.npz", labels=lambda v: v.labels + 0.5),
        _reader,
        ValueError,
        "non-integer values",
    ),
    (
        _npz("seg.npz", labels=lambda v: v.labels, spacing=np.full(3, 1e-3)),
        _reader,
        ValueError,
        r"the breast is 0\.085 mm across .* Set reader\.units",
    ),
    (_npz("seg.npz", labels=lambda v: 7 * v.labels), _reader, ValueError, r"value\(s\) \[7, 14"),
    (lambda t, v, m: t / "missing.nii.gz", _reader, FileNotFoundError, "no such file"),
    (lambda t, v, m: _folder(t / "case.nii.gz"), _reader, ValueError, "a folder, not a file"),
    # meshes (any meshio format)
    (_bytes("breast.vtu", b"hello"), _reader, ValueError, "not a mesh meshio reads"),
    (_empty("breast.msh"), _reader, ValueError, "the file is empty"),
    (_vtu(scale=1e-3), _reader, ValueError, r"the breast is 0\.132 mm across .* Set reader\.units"),
    (_vtu(scale=1e3), _reader, ValueError, r"mm across .* another unit"),
    (_vtu(nan=True), _reader, ValueError, "NaN or infinite coordinates"),
    (_vtu(bad_index=True), _reader, ValueError, "indexes nodes outside"),
    # trajectories (Trajectory.load: the cohort, the data module, the report, the readers)
    (_empty("breast.npz"), Trajectory.load, ValueError, "the file is empty"),
    (
        lambda t, v, m: _truncated(m.save(t / "breast.npz")),
        Trajectory.load,
        ValueError,
        "truncated or corrupt",
    ),
    (
        _npz("breast.npz", labels=lambda v: v.labels),
        Trajectory.load,
        ValueError,
        "not a trajectory file: field 'schema_version' is missing",
    ),
    (
        _trajectory(metadata=np.array("{nope")),
        Trajectory.load,
        ValueError,
        "field 'metadata' is not a JSON object",
    ),
    (
        _trajectory(cells=np.zeros((3, 4))),
        Trajectory.load,
        ValueError,
        "field 'cells' holds float64 values, not integers",
    ),
    (_trajectory(), BreastReader(units="m"), ValueError, "a trajectory file is in mm"),
    # model files (mammo_net.baselines, as load_surrogate and predict.py read them)
    (_bytes("model.json", b"{nope"), load_xgboost, ValueError, "truncated or corrupt"),
    (_empty("model.ubj"), load_xgboost, ValueError, "the file is empty"),
    (_bytes("model.ubj", b"\x00junk"), load_xgboost, ValueError, "it is not an XGBoost model"),
    (_bytes("model.json", b"PK\x03\x04junk"), load_xgboost, ValueError, r"a ZIP archive"),
    (_foreign_xgboost, load_xgboost, ValueError, r"another model: .* 1 output\(s\)"),
    (_schemaless_xgboost, load_surrogate, ValueError, "the file has no feature schema"),
    (
        _npz("ert.npz", a=np.zeros(3)),
        load_forest,
        ValueError,
        "not an ERT model file: field\\(s\\) 'left'",
    ),
    (lambda t, v, m: _forest(t, _cycle), load_forest, ValueError, "children must follow"),
    (
        lambda t, v, m: _forest(t, _far_feature, FeatureSchema.of("unloaded", 100)),
        load_forest,
        ValueError,
        "not below the schema's 11 features",
    ),
    (lambda t, v, m: _truncated(_forest(t)), load_surrogate, ValueError, "truncated or corrupt"),
    # landmarks (predict.py landmarks=...)
    (_bytes("lm.csv", b"\xfc\xfd\x00\x01"), read_landmarks, ValueError, "UnicodeDecodeError"),
]


@pytest.mark.parametrize(
    ("make", "load", "error", "message"),
    BAD_FILES,
    ids=[f"{i:02d}-{m}" for i, (*_, m) in enumerate(BAD_FILES)],
)
def test_a_bad_file_gets_one_error_naming_it(
    tmp_path, ellipsoid_volume, breast_mesh, make, load, error, message
):
    path = make(tmp_path, ellipsoid_volume, breast_mesh)
    before = sorted(tmp_path.iterdir())
    with pytest.raises(error, match=message) as info:
        load(path)
    assert type(info.value) is error
    assert str(path) in str(info.value)
    assert "allow_pickle" not in str(info.value)
    assert sorted(tmp_path.iterdir()) == before


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"spacing": [0, 0, 0]}, r"reader\.spacing must be three finite voxel sizes > 0"),
        ({"spacing": [1, 1]}, r"reader\.spacing must be three"),
        ({"units": "inch"}, r"reader\.units is 'inch'; use mm, cm, m"),
        ({"orientation": "RAR"}, r"reader\.orientation is 'RAR': give three letters"),
        ({"extent_mm": [500, 20]}, r"reader\.extent_mm must be two sizes"),
        ({"label_map": {"glands": 2}}, r"reader\.label_map: unknown tissue 'glands'"),
        ({"label_map": {"fat": "one"}}, r"reader\.label_map\.fat must be an integer"),
        (
            {"label_map": {"fat": [1, 3], "muscle": 3}},
            r"reader\.label_map: value 3 is mapped to fat and to muscle",
        ),
    ],
)
def test_bad_reader_settings_are_refused_before_reading(settings, message):
    with pytest.raises(ValueError, match=message):
        BreastReader(**settings)


def _mesh_breast_cfg(path: Path, *overrides: str):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(
            "mesh_breast",
            overrides=[f"input={path}", f"output={path.parent / 'out' / 'case'}", *overrides],
        )


#: A bad setting reaches the command inside Hydra's InstantiationException (its message
#: quotes the ValueError); a bad file as the reader's ValueError.
SETTING = InstantiationException


@pytest.mark.parametrize(
    ("make", "overrides", "error", "message"),
    [
        (_empty("seg.nrrd"), [], ValueError, "seg.nrrd: the file is empty"),
        (
            lambda t, v, m: _nifti(t, v),
            ["reader.label_map.fat=[1,3]"],
            SETTING,
            "value 3 is mapped to fat and to muscle",
        ),
        (
            lambda t, v, m: _nifti(t, v),
            ["reader.label_map.skin=3"],
            SETTING,
            r"value 3 is mapped to muscle and to skin.* reader\.label_map\.muscle=\[\]",
        ),
        (lambda t, v, m: _nifti(t, v), ["reader.spacing=[0,0,0]"], SETTING, "reader.spacing"),
        (lambda t, v, m: _nifti(t, v), ["reader.units=um"], SETTING, "reader.units is 'um'"),
        (_vtu(scale=1e-3), [], ValueError, "breast.vtu: the breast is .* reader.units"),
        (_bytes("breast.vtu", b"<VTKFile>"), [], ValueError, "breast.vtu: cannot be read"),
    ],
)
def test_mesh_breast_writes_nothing_on_a_bad_input(
    tmp_path, ellipsoid_volume, breast_mesh, make, overrides, error, message
):
    from fem.mesh_breast import mesh_breast

    path = make(tmp_path, ellipsoid_volume, breast_mesh)
    cfg = _mesh_breast_cfg(path, *overrides)
    with pytest.raises(error, match=message) as info:
        mesh_breast(cfg)
    assert type(info.value) is error
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (_bytes("breast.vtu", b"junk"), "breast.vtu: cannot be read as a mesh"),
        (_vtu(scale=1e-3), "breast.vtu: the breast is 0.132 mm across"),
    ],
)
def test_simulate_writes_nothing_on_a_bad_input(
    tmp_path, ellipsoid_volume, breast_mesh, make, message
):
    from fem.simulate import simulate_file

    path = make(tmp_path, ellipsoid_volume, breast_mesh)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("simulate", overrides=[f"input={path}", f"output={tmp_path / 'out' / 'c'}"])
    with pytest.raises(ValueError, match=message) as info:
        simulate_file(cfg)
    assert type(info.value) is ValueError
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


# --- the commands: train.py, predict.py, fem.cohort, mammo_net.report ---------------------------
#
# Each bad setting or file gets ONE error of exactly the type named, whose message names the
# setting (as ``key=value`` is written on the command line) or the file. It is raised before
# anything is written: the folder the command ran in holds the same files afterwards (no
# output folder, no feature cache, no cohort folder), and no cohort is built first.


def _tree(folder: Path) -> list[tuple[str, bytes]]:
    """Every path under ``folder``, relative, with a file's content (a folder's: empty)."""
    return sorted(
        (str(p.relative_to(folder)), b"" if p.is_dir() else p.read_bytes())
        for p in folder.rglob("*")
    )


def _refused_leaving_nothing(
    folder: Path, error: type[Exception], message: str, command, *args
) -> None:
    """``command(*args)`` raises exactly ``error`` matching ``message``, and ``folder`` is left
    as it was."""
    before = _tree(folder)
    with pytest.raises(error, match=message) as info:
        command(*args)
    assert type(info.value) is error
    assert _tree(folder) == before


@pytest.fixture
def no_cohort_built(monkeypatch):
    """Fail the test where a cohort's breasts would be generated: the settings passed."""
    from fem import cohort as cohort_command

    monkeypatch.setattr(cohort_command, "cohort_executor", lambda *_: pytest.fail("cohort built"))


BAD_TRAIN = [
    # data (data.data_dir defaults to the cohort's folder, which would be built first)
    (["data.data_dir={tmp}/empty"], FileNotFoundError, r"empty: no simulated trajectories"),
    (["data.data_dir={tmp}/absent"], FileNotFoundError, r"absent: no simulated trajectories"),
    (["data.data_dir={tmp}/junk"], ValueError, r"junk/P0000_L\.npz: it is not a trajectory"),
    (["data.step=bogus"], SETTING, r"data\.step must be one of \['compression', 'unloaded'\]"),
    (["data.fold=12"], SETTING, r"data\.fold must be in 0\.\.9 for k_fold \(data\.n_folds=10\)"),
    (["data.split=bogus"], SETTING, r"data\.split must be 'one_fold' or 'k_fold'"),
    (["data.split=one_fold", "data.fold=2"], SETTING, r"data\.fold=2 selects a k-fold"),
    (["data.fold=0", "data.n_folds=1"], SETTING, r"data\.n_folds must be at least 2"),
    (["data.data_dir=[{tmp}/a/trajectories,{tmp}/a/trajectories]"], SETTING,
     r"data\.data_dir: \[.*a/trajectories'\] given twice or holding another"),
    (["data.train_conditions={{young_bone:[1,2]}}"], SETTING,
     r"data\.train_conditions\.young_bone: unknown condition"),
    (["data.train_conditions={{friction:[0.5,0.1]}}"], SETTING,
     r"data\.train_conditions\.friction must be \[low, high\]"),
    # model
    (["model.step=bogus"], SETTING, r"model\.step must be one of"),
    (["data.step=unloaded", "model.step=compression"], ValueError,
     r"model\.step=compression .*data\.step=unloaded"),
    (["model.lr_schedule=warm"], SETTING, r"model\.lr_schedule must be 'constant' or 'cosine'"),
    # the cohort train.py builds, and the run folder
    (["cohort.workers=0"], ValueError, r"workers must be an integer >= 1, got 0"),
    (["cohort.executor=bogus"], ValueError, r"executor must be one of \('local', 'dask'\)"),
    (["cohort.mesher.target_elements=0"], SETTING, r"mesher\.target_elements must be at least 1"),
    (["run_dir={tmp}/file"], PermissionError, r"file: cannot write output files there"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("overrides", "error", "message"),
    BAD_TRAIN,
    ids=[" ".join(o).replace("{tmp}/", "") for o, *_ in BAD_TRAIN],
)
def test_train_refuses_before_building_or_training(
    tmp_path, no_cohort_built, overrides, error, message
):
    import train

    (tmp_path / "empty").mkdir()
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "P0000_L.npz").write_bytes(b"junk")
    (tmp_path / "file").write_text("")
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"run_dir={tmp_path / 'run'}",
                f"cohort.out_dir={tmp_path / 'cohort'}",
                *(o.format(tmp=tmp_path) for o in overrides),
            ],
        )
    _refused_leaving_nothing(tmp_path, error, message, train.train, cfg)


def _predict_inputs(tmp: Path, model_dir: Path) -> None:
    """The files the bad requests name: a breast with and one without laterality, landmarks
    outside it, a truncated checkpoint, a checkpoint of no network, a file for a folder."""
    import torch

    scheduled_trajectory(0.7).save(tmp / "case.npz")
    no_side = scheduled_trajectory(0.7)
    no_side.metadata.pop("laterality")
    no_side.save(tmp / "nolat.npz")
    (tmp / "far.csv").write_text("x,y,z\n100,100,100\n")
    (tmp / "half.ckpt").write_bytes((model_dir / "unloaded.ckpt").read_bytes())
    _truncated(tmp / "half.ckpt")
    torch.save({"weights": [1.0]}, tmp / "other.ckpt")
    (tmp / "file").write_text("")


#: predict.py's requests on ``{tmp}/case.npz`` at 0.7 mm unless they say otherwise.
BAD_PREDICT = [
    # thickness
    (["thickness=5"], ValueError,
     r"case\.npz: compressed thickness 5\.0 mm is not smaller than the breast's cranio-caudal"),
    (["thickness=0"], ValueError, r"thickness must be a compressed thickness in mm \(> 0\).*got 0"),
    (["thickness=-1"], ValueError, r"thickness must be .*got -1"),
    (["thickness=[]"], ValueError, r"thickness must be .* a non-empty list of them, got \[\]"),
    (["thickness=thin"], ValueError, r"thickness must be .*got 'thin'"),
    (["thickness=[50,nan]"], ValueError, r"thickness must be .*got \[50, nan\]"),
    # landmarks
    (["landmarks={tmp}/far.csv"], ValueError,
     r"far\.csv: landmark '1' at \[100\.0, 100\.0, 100\.0\] mm lies outside the breast mesh"),
    (["landmarks={tmp}/absent.csv"], FileNotFoundError, r"absent\.csv: no such file"),
    # model files
    (["unloaded_model={models}/compression.json"], ValueError,
     r"compression\.json: the model predicts the compression step, not the unloaded step"),
    (["unloaded_model={tmp}/absent.ckpt"], FileNotFoundError, r"absent\.ckpt: no such file"),
    (["compression_model={tmp}/absent.json"], FileNotFoundError, r"absent\.json: no such file"),
    (["compression_model={tmp}/model.pkl"], ValueError, r"model\.pkl: a model file ends in one of"),
    (["unloaded_model={tmp}/half.ckpt"], ValueError,
     r"half\.ckpt: cannot be read as a Lightning checkpoint \(\.ckpt\): the file is truncated"),
    (["unloaded_model={tmp}/other.ckpt"], ValueError,
     r"other\.ckpt: not a checkpoint of a trained network"),
    (["unloaded_model={tmp}/case.npz"], ValueError, r"case\.npz: not an ERT model file"),
    (["precision=fp8"], ValueError, r"precision must be one of \('32-true', 'bf16-mixed'\)"),
    # laterality
    (["laterality=X"], ValueError, r"laterality must be L, R or null \(the file's\), got 'X'"),
    (["input={tmp}/nolat.npz"], ValueError,
     r"nolat\.npz: metadata field 'laterality' must be 'L' or 'R', got None: set laterality=L"),
    # the input, the checks, the output folder
    (["input={tmp}/absent.vtu"], FileNotFoundError, r"absent\.vtu: no such file"),
    (["checks.on_violation=bogus"], SETTING, r"checks\.on_violation must be 'warn' or 'refuse'"),
    (["checks.max_volume_change=-1"], SETTING, r"checks\.max_volume_change must be >= 0"),
    (["out_dir={tmp}/file/case"], PermissionError, r"file: cannot write output files there"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("overrides", "error", "message"),
    BAD_PREDICT,
    ids=[" ".join(o).replace("{tmp}/", "").replace("{models}/", "") for o, *_ in BAD_PREDICT],
)
def test_predict_refuses_before_writing(models, tmp_path, overrides, error, message):  # noqa: F811
    import predict

    _predict_inputs(tmp_path, models)
    cfg = _predict_cfg(
        models,
        tmp_path,
        f"input={tmp_path / 'case.npz'}",
        "thickness=0.7",
        *(o.format(tmp=tmp_path, models=models) for o in overrides),
    )
    _refused_leaving_nothing(tmp_path, error, message, predict.predict, cfg)


BAD_COHORT = [
    (["workers=0"], ValueError, r"workers must be an integer >= 1, got 0"),
    (["workers=-2"], ValueError, r"workers must be an integer >= 1, got -2"),
    (["n_patients=0"], ValueError, r"n_patients must be an integer >= 1, got 0"),
    (["n_patients=-3"], ValueError, r"n_patients must be an integer >= 1, got -3"),
    (["executor=bogus"], ValueError, r"executor must be one of \('local', 'dask'\), got 'bogus'"),
    (["scheduler=tcp://localhost:8786"], ValueError,
     r"scheduler=tcp://localhost:8786 is a Dask scheduler's address: it needs executor=dask"),
    (["simulate=true", "simulation.friction=-1"], SETTING, r"simulation\.friction must be >= 0"),
    (["simulate=true", "simulation.fascia_stiffness=-1"], SETTING,
     r"simulation\.fascia_stiffness must be >= 0 Pa/mm"),
    (["simulate=true", "simulation.materials.fat.young=0"], SETTING,
     r"simulation\.materials\.fat: young must be > 0 Pa"),
    (["simulate=true", "simulation.compression_ratio=1.5"], SETTING,
     r"simulation\.compression_ratio must lie in \(0, 1\)"),
    (["simulate=true", "simulation.compression_steps=0"], SETTING,
     r"simulation\.compression_steps must be at least 1"),
    (["simulate=true", "simulation.materials.fat.poisson=0.5"], SETTING,
     r"simulation\.materials\.fat: young must be > 0"),
    (["simulate=true", "simulation.view=ml"], SETTING,
     r"simulation\.view must be one of \('cc', 'mlo'\), got 'ml'"),
    (["simulate=true", "simulation.chest_wall=glued"], SETTING,
     r"simulation\.chest_wall must be one of \('sliding', 'tied', 'anteroposterior', 'none'\)"),
    (["simulate=true", "simulation.angle=120"], SETTING, r"simulation\.angle must lie in \[0, 90\]"),
    (["simulate=true", "simulation.compression_gravity=[0,-9.81]"], SETTING,
     r"simulation\.compression_gravity must be 3 numbers"),
    (["simulate=true", "+simulation.materials.fascia.young=3000"], SETTING,
     r"simulation\.materials\.fascia: 'fascia' is not a tissue .* give its elements file"),
    (["simulate=true", "+simulation.materials.fat.mu=300"], SETTING,
     r"simulation\.materials\.fat: give young \(and poisson\) or mu and kappa"),
    (["simulate=true", "+simulation.plates.lower.origin=[0,0,0]"], SETTING,
     r"simulation\.plates\.lower\.normal must be 3 numbers"),
    (["refine=-1"], ValueError, r"refine must be an integer >= 0, got -1"),
    (["mesher.target_elements=0"], SETTING, r"mesher\.target_elements must be at least 1, got 0"),
    (["mesher.min_quality=1.5"], SETTING, r"mesher\.min_quality must lie in \[0, 1\)"),
    (["mesher.max_attempts=0"], SETTING, r"mesher\.max_attempts must be at least 1"),
    (["generator.voxel_size=0"], SETTING, r"generator\.voxel_size must be > 0 mm"),
    (["out_dir={tmp}/file/cohort"], PermissionError, r"file: cannot write output files there"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("overrides", "error", "message"),
    BAD_COHORT,
    ids=[" ".join(o).replace("{tmp}/", "") for o, *_ in BAD_COHORT],
)
def test_cohort_refuses_before_creating_its_folder(
    tmp_path, no_cohort_built, overrides, error, message
):
    from fem.cohort import run_cohort

    (tmp_path / "file").write_text("")
    cfg = _cohort_cfg(tmp_path / "cohort", *(o.format(tmp=tmp_path) for o in overrides))
    _refused_leaving_nothing(tmp_path, error, message, run_cohort, cfg)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("generator.seed=1", r"generator\.seed: 0 there, 1 now"),
        ("mesher.target_elements=900", r"mesher\.target_elements: 2250 there, 900 now"),
    ],
)
def test_cohort_refuses_to_resume_with_other_settings(tmp_path, no_cohort_built, override, message):
    """A cohort folder's breasts were made with other settings: refused naming each key, its
    record (``cohort_config.json``) unchanged."""
    from fem.cohort import check_settings, run_cohort

    folder = tmp_path / "cohort"
    folder.mkdir()
    check_settings(folder, _cohort_cfg(folder))  # the record of a first run
    message = r"cohort_config\.json: the breasts in .* other settings: " + message
    _refused_leaving_nothing(
        tmp_path, ValueError, message, run_cohort, _cohort_cfg(folder, override)
    )


def test_cohort_of_before_the_refine_setting_resumes_unrefined_only(tmp_path, no_cohort_built):
    """A folder recorded before ``refine`` existed was simulated unrefined: it resumes with
    ``refine=0`` and refuses ``refine=1`` by name."""
    import json

    from fem.cohort import check_settings

    folder = tmp_path / "cohort"
    folder.mkdir()
    check_settings(folder, _cohort_cfg(folder, "simulate=true"))
    record = folder / "cohort_config.json"
    stored = json.loads(record.read_text())
    assert stored.pop("refine") == 0
    record.write_text(json.dumps(stored))
    check_settings(folder, _cohort_cfg(folder, "simulate=true"))
    with pytest.raises(ValueError, match=r"refine: 0 there, 1 now"):
        check_settings(folder, _cohort_cfg(folder, "simulate=true", "refine=1"))


def _prediction_file(runs: Path) -> Path:
    return runs / "fold0" / "predictions" / "model.npz"


def _timing_file(runs: Path) -> Path:
    return _prediction_file(runs).with_suffix(".json")


def _write(path_of, data: bytes | str):
    """A case that writes ``data`` to the file ``path_of(runs)``."""

    def make(runs: Path) -> dict:
        path = path_of(runs)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return {}

    return make


def _truncated_predictions(runs: Path) -> dict:
    _truncated(_prediction_file(runs))
    return {}


def _predictions(**arrays):
    """A case that replaces fold0's predictions with ``arrays``."""

    def make(runs: Path) -> dict:
        np.savez(_prediction_file(runs), **arrays)
        return {}

    return make


def _lone_run(file: str, data: bytes | str):
    """A case that reports on the run folder ``runs/bad`` alone, holding ``data`` in ``file``."""
    write = _write(lambda runs: runs / "bad" / file, data)
    return lambda runs: write(runs) | {"runs": [runs / "bad"]}


def _settings(data: str):
    """A case on a lone run folder whose ``.hydra/config.yaml`` holds ``data``."""
    return _lone_run(".hydra/config.yaml", data)


_RUN_DATA = "data:\n  data_dir: trajectories\n  "

#: The report over the test_report cohort's run folders (``runs/*``) into ``report/``; each
#: case changes a file, and returns the arguments it changes.
BAD_REPORT = {
    "no run folder matches": (
        lambda runs: {"runs": [runs / "nothing*"]}, FileNotFoundError,
        r"runs: no run folder matches \['.*nothing\*'\]"),
    "truncated predictions": (
        _truncated_predictions, ValueError,
        r"fold0/predictions/model\.npz: cannot be read as a predictions file \(\.npz\): the "
        r"file is truncated or corrupt"),
    "junk predictions": (
        _write(_prediction_file, b"junk"), ValueError,
        r"fold0/predictions/model\.npz: it is not a predictions file"),
    "pickled predictions": (
        _predictions(P0000_L=np.array([{}], dtype=object)), ValueError,
        r"fold0/predictions/model\.npz: .*pickled Python objects, which are never loaded"),
    "predictions of another shape": (
        _predictions(P0000_L=np.zeros((5, 2, 3))), ValueError,
        r"fold0/predictions/model\.npz: field 'P0000_L' has shape \(5, 2, 3\), the FE "
        r"trajectory \(5, 3, 3\)"),
    "a breast without trajectory": (
        _predictions(P0009_L=np.zeros((5, 3, 3))), FileNotFoundError,
        r"trajectories/P0009_L\.npz: no such file"),
    "junk timing file": (
        _write(_timing_file, "{nope"), ValueError,
        r"fold0/predictions/model\.json: cannot be read as a prediction timing file"),
    "timing file of words": (
        _write(_timing_file, '{"seconds": {"P0000_L": "fast"}}'), ValueError,
        r"fold0/predictions/model\.json: field 'seconds' must map breast names to seconds"),
    "no predictions nor models": (
        _settings(_RUN_DATA + "step: compression\n"), FileNotFoundError,
        r"no predictions/\*\.npz, nor model files to predict them with .* in \['.*bad'\]"),
    "no run config": (
        _lone_run("predictions/model.npz", b""), FileNotFoundError,
        r"bad/\.hydra/config\.yaml: not found; is .*bad a train\.py run folder"),
    "run config step": (
        _settings(_RUN_DATA + "step: bogus\n"), ValueError,
        r"bad/\.hydra/config\.yaml: data\.step must be one of"),
    "run config fold": (
        _settings(_RUN_DATA + "fold: 12\n"), ValueError,
        r"bad/\.hydra/config\.yaml: data\.fold must be in 0\.\.9"),
    "data_dir without the breasts": (
        lambda runs: {"data_dir": runs}, FileNotFoundError, r"runs/P0000_L\.npz: no such file"),
    "out_dir inside a file": (
        lambda runs: {"out_dir": runs / "fold0" / ".hydra" / "config.yaml" / "report"},
        PermissionError, r"config\.yaml: cannot write output files there .*: it is a file"),
}  # fmt: skip


@pytest.mark.parametrize(
    ("make", "error", "message"), list(BAD_REPORT.values()), ids=list(BAD_REPORT)
)
def test_report_refuses_before_writing(cohort, make, error, message):  # noqa: F811
    analysis = OmegaConf.load(Path(CONF) / "analysis" / "default.yaml")
    arguments = {"runs": [cohort / "*"], "out_dir": cohort.parent / "report", "analysis": analysis}
    report = functools.partial(write_report, **arguments | make(cohort))
    _refused_leaving_nothing(cohort.parent, error, message, report)


# --- a killed cohort (slow) ------------------------------------------------------------------

SETTINGS = (
    "n_patients=2",
    "workers=2",
    "figures=false",
    "mesher.target_elements=700",
    "mesher.tolerance=200",
    "simulation.unloaded_steps=4",
    "simulation.compression_steps=5",
)


def _cohort(out: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fem.cohort", f"out_dir={out}", *SETTINGS],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def _processes_writing(out: Path) -> list[int]:
    """PIDs of live processes whose command line names ``out`` (the command and its workers)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().decode(errors="replace")
            state = (proc / "stat").read_text().split()[2]
        except OSError:
            continue
        if proc.name.isdigit() and str(out) in cmd and state != "Z":
            pids.append(int(proc.name))
    return pids


def _arrays(folder: Path) -> dict[str, dict[str, np.ndarray]]:
    return {
        p.name: {f.name: getattr(t, f.name) for f in fields(Trajectory) if f.name != "metadata"}
        for p in sorted(folder.glob("P*.npz"))
        for t in [Trajectory.load(p)]
    }


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_three_kills_then_resume_equal_an_uninterrupted_run(tmp_path):
    rng = random.Random(0)
    killed = tmp_path / "killed"
    for _ in range(3):
        proc = _cohort(killed)
        time.sleep(rng.uniform(2.0, 8.0))
        os.kill(proc.pid, signal.SIGKILL)  # the command only: its workers must follow alone
        proc.wait()
        deadline = time.monotonic() + 10
        while _processes_writing(killed) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _processes_writing(killed), "a worker outlived the killed command"
    assert _cohort(killed).wait() == 0
    clean = tmp_path / "clean"
    assert _cohort(clean).wait() == 0
    for stage in ("", "trajectories"):
        got, expected = _arrays(killed / stage), _arrays(clean / stage)
        assert sorted(got) == sorted(expected) and len(got) == 4
        for name, arrays in expected.items():
            for field, value in arrays.items():
                np.testing.assert_array_equal(got[name][field], value, err_msg=f"{name} {field}")
