"""Bad input gets one clear error that names the file or the setting, and leaves no output.

The corpus grows per command; docs/reliability.md tabulates it."""

from __future__ import annotations

from pathlib import Path

import meshio
import nibabel
import nrrd
import numpy as np
import pytest
import xgboost as xgb
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException

from datamodules.features import FeatureSchema
from datamodules.trajectories import TrajectoryDataModule
from fem.breasts.io import BreastReader
from fem.contract.trajectory import Trajectory
from mammo_net.baselines import fit_ert, fit_xgboost, load_forest, load_xgboost, save_xgboost
from mammo_net.predictor import load_surrogate, read_landmarks
from mammo_net.report import write_report

CONF = str(Path(__file__).resolve().parents[1] / "conf")


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
