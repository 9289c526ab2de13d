"""Several trajectory folders (the cohort v2's views) as one data set, the training set's bounds
on the simulation conditions (``data.train_conditions``), and the held-out-conditions
benchmark, on tiny synthetic v2-like trajectories."""

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SIMULATION_METADATA, benchmark_module, tiny_trajectory
from omegaconf import OmegaConf

from datamodules.graphs import MeshGraphDataModule
from datamodules.trajectories import TrajectoryDataModule, cache_is_current, folder_labels
from mammo_net.module import MeshGraphModule, NetworkModule
from mammo_net.stiffness_range import record_stiffness_range

#: Patient p's fat modulus (Pa); bounds [700, 2600] hold patients 0, 6 and 7 out.
FAT = (550.0, 800.0, 1100.0, 1500.0, 2000.0, 2500.0, 3000.0, 3300.0)
BOUNDS = {"young_fat": [700, 2600]}


def mlo_angle(patient: int) -> float:
    return 40.0 + 2.0 * patient


def simulation(patient: int, view: str) -> dict:
    sim = copy.deepcopy(SIMULATION_METADATA)
    sim["materials"]["fat"]["young"] = FAT[patient]
    sim["view"] = view
    sim["angle"] = mlo_angle(patient) if view == "mlo" else 45.0
    return sim


@pytest.fixture
def views(tmp_path) -> list[Path]:
    """A v2-like cohort: 8 patients (2 of site A), both breasts, in ``trajectories/`` (cc) and
    ``trajectories_mlo/`` (mlo) under the same file names, each with its own conditions."""
    folders = [tmp_path / "v2" / "trajectories", tmp_path / "v2" / "trajectories_mlo"]
    for folder, view in zip(folders, ("cc", "mlo"), strict=True):
        folder.mkdir(parents=True)
        for p in range(8):
            for lat in "LR":
                site = "A" if p % 4 == 0 else "B"
                traj = tiny_trajectory(lat, patient=p, site=site, simulation=simulation(p, view))
                traj.save(folder / f"P{p:04d}_{lat}.npz")
    return folders


def _setup(cls, folders, **kwargs):
    dm = cls([str(f) for f in folders], n_folds=4, fold=1, **kwargs)
    dm.prepare_data()
    dm.setup()
    return dm


def _patient(name: str) -> int:
    return int(name[1:5])


@pytest.mark.parametrize("cls", [TrajectoryDataModule, MeshGraphDataModule])
def test_two_folders_name_breasts_apart_and_split_by_patient(views, cls):
    dm = _setup(cls, views)
    names = [b.name for b in dm.train + dm.val]
    assert len(set(names)) == len(names) == 32
    assert {n.split("@")[1] for n in names} == {"trajectories", "trajectories_mlo"}
    # both views of both breasts of a patient on one side
    val = {b.patient for b in dm.val}
    assert not val & {b.patient for b in dm.train} and len(val) == 2
    assert len(dm.val) == 4 * len(val)
    # each folder keeps its own cache; a name leads back to its file
    kind = dm.cache_kind
    for folder in views:
        assert (folder / "cache" / kind / "P0003_R.json").exists()
    assert dm.source("P0003_R@trajectories_mlo") == views[1] / "P0003_R.npz"
    with pytest.raises(ValueError, match=r"P0003_R@elsewhere.*none of the data folders"):
        dm.source("P0003_R@elsewhere")
    assert dm.hparams.data_dir == [str(f) for f in views]  # as given


def test_one_folder_keeps_its_names_and_cache_dir_splits_by_folder(views, tmp_path):
    one = TrajectoryDataModule(str(views[1]), cache_dir=str(tmp_path / "c1"))
    assert [s.name for s in one.sources()][:2] == ["P0000_L", "P0000_R"]
    assert one.sources()[0].stem == tmp_path / "c1" / "compression" / "P0000_L"
    both = TrajectoryDataModule([str(f) for f in views], cache_dir=str(tmp_path / "c2"))
    stems = {s.name: s.stem for s in both.sources()}
    assert stems["P0000_L@trajectories_mlo"] == (
        tmp_path / "c2" / "trajectories_mlo" / "compression" / "P0000_L"
    )
    assert stems["P0000_L@trajectories"].parents[1] == tmp_path / "c2" / "trajectories"


def test_folders_of_one_name_are_labelled_by_their_path(views, tmp_path):
    """Two cohorts' ``trajectories`` folders (say, two mesh resolutions) name their breasts by
    the path below the common parent, and each name leads back to its file."""
    other = tmp_path / "2x" / "trajectories"
    shutil.copytree(views[0], other)
    assert folder_labels([views[0], other]) == ["v2-trajectories", "2x-trajectories"]
    assert folder_labels(views) == ["trajectories", "trajectories_mlo"]
    dm = TrajectoryDataModule([str(views[0]), str(other)], cache_dir=str(tmp_path / "c"))
    sources = {s.name: s for s in dm.sources()}
    assert len(sources) == 32
    assert sources["P0003_R@2x-trajectories"].path == other.absolute() / "P0003_R.npz"
    assert sources["P0003_R@2x-trajectories"].stem.parents[1] == tmp_path / "c" / "2x-trajectories"
    assert dm.source("P0003_R@v2-trajectories") == views[0].absolute() / "P0003_R.npz"
    with pytest.raises(ValueError, match=r"breast 'P0003_R@trajectories': none of the data"):
        dm.source("P0003_R@trajectories")


@pytest.mark.parametrize("cls", [TrajectoryDataModule, MeshGraphDataModule])
def test_augmentation_folders_add_training_breasts_only(views, tmp_path, cls):
    """``augment_dir`` (the breasts remeshed at other resolutions): its breasts of training
    patients join the training set under their folder's label, those of validation patients
    are left out; the split, the validation set and the data folder's names stay as without."""
    plain = _setup(cls, views[:1])
    finer = tmp_path / "resolution" / "2x" / "trajectories"
    finer.mkdir(parents=True)
    train, val = [b.name for b in plain.train[:3]], [b.name for b in plain.val[:2]]
    for name in train + val:
        shutil.copy(views[0] / f"{name}.npz", finer / f"{name}.npz")
    dm = _setup(cls, views[:1], augment_dir=[str(finer)])
    assert [b.name for b in dm.val] == [b.name for b in plain.val]
    added = sorted(b.name for b in dm.train if "@" in b.name)
    assert added == [f"{name}@resolution-2x-trajectories" for name in sorted(train)]
    assert {b.name for b in dm.train} - set(added) == {b.name for b in plain.train}
    assert dm.source(added[0]) == finer.absolute() / f"{sorted(train)[0]}.npz"
    assert dm.source(val[0]) == views[0].absolute() / f"{val[0]}.npz"
    assert (finer / "cache" / dm.cache_kind / f"{train[0]}.json").exists()
    assert dm.hparams.augment_dir == [str(finer)]
    run = _run_folder(
        tmp_path / "run",
        {"cohort": views[0].parent, "data_dir": str(views[0]), "fold": 1,
         "augment_dir": [str(finer)]},
    )  # fmt: skip
    assert TrajectoryDataModule.from_run(run).augment_dirs == [finer.absolute()]
    # a fixed share: at most augment_limit of the folder's training breasts, the same draw twice
    limited = [
        sorted(
            b.name
            for b in _setup(cls, views[:1], augment_dir=[str(finer)], augment_limit=2).train
            if "@" in b.name
        )
        for _ in range(2)
    ]
    assert limited[0] == limited[1] and len(limited[0]) == 2 and set(limited[0]) < set(added)
    with pytest.raises(ValueError, match=r"data\.augment_limit must be a positive number"):
        cls(str(views[0]), augment_dir=[str(finer)], augment_limit=0)
    with pytest.raises(ValueError, match=r"data\.augment_limit must be a positive number"):
        cls(str(views[0]), augment_dir=[str(finer)], augment_limit="many")
    bad = _run_folder(tmp_path / "bad", {"cohort": tmp_path, "data_dir": "x", "augment_dir": 3})
    with pytest.raises(ValueError, match=r"field 'data\.augment_dir' must be str or list of str"):
        TrajectoryDataModule.from_run(bad)


def test_data_folders_refused(views, tmp_path):
    with pytest.raises(ValueError, match=r"given twice or holding another"):
        TrajectoryDataModule([str(views[0]), str(views[1]), str(views[0])])
    with pytest.raises(ValueError, match=r"given twice or holding another"):
        TrajectoryDataModule([str(views[0]), str(views[0] / "sub")])
    with pytest.raises(ValueError, match="empty list"):
        TrajectoryDataModule([])
    with pytest.raises(ValueError, match=r"^data\.augment_dir: an empty list"):
        TrajectoryDataModule(str(views[0]), augment_dir=[])
    with pytest.raises(ValueError, match=r"^data\.data_dir and data\.augment_dir: .* given twice"):
        TrajectoryDataModule(str(views[0]), augment_dir=[str(views[1]), str(views[0])])
    empty = tmp_path / "empty_view"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="empty_view: no simulated trajectories"):
        TrajectoryDataModule([str(views[0]), str(empty)]).prepare_data()


@pytest.mark.parametrize("cls", [TrajectoryDataModule, MeshGraphDataModule])
def test_train_conditions_drop_training_breasts_outside_the_bounds(views, cls):
    everything = _setup(cls, views)
    bounds = {**BOUNDS, "angle": [41, 60]}
    dm = _setup(cls, views, train_conditions=bounds)
    assert [b.name for b in dm.val] == [b.name for b in everything.val]  # all kept

    def inside(name: str) -> bool:
        p = _patient(name)
        angle_ok = name.endswith("@trajectories") or 41 <= mlo_angle(p) <= 60
        return 700 <= FAT[p] <= 2600 and angle_ok

    expected = [b.name for b in everything.train if inside(b.name)]
    assert [b.name for b in dm.train] == expected
    assert 0 < len(expected) < len(everything.train)
    assert any(not inside(b.name) for b in dm.val)  # held-out breasts are evaluated
    assert dm.hparams.train_conditions == {"young_fat": [700.0, 2600.0], "angle": [41.0, 60.0]}


def test_train_conditions_refused(views, tmp_path):
    folders = [str(f) for f in views]
    for bounds, message in [
        ({"young_bone": [1, 2]}, r"data\.train_conditions\.young_bone: unknown condition"),
        ({"friction": [0.1]}, r"data\.train_conditions\.friction must be \[low, high\]"),
        ({"friction": [0.5, 0.1]}, r"data\.train_conditions\.friction must be"),
        ({"young_fat": "700-2600"}, r"data\.train_conditions\.young_fat must be"),
        ({"young_fat": [700, float("nan")]}, r"data\.train_conditions\.young_fat must be"),
        ([700, 2600], "must map condition names"),
    ]:
        with pytest.raises(ValueError, match=message):
            TrajectoryDataModule(folders, train_conditions=bounds)
    with pytest.raises(ValueError, match=r"no training breast .* lies within the bounds"):
        _setup(TrajectoryDataModule, views, train_conditions={"young_fat": [10, 20]})
    # a trajectory that does not record its conditions cannot be bounded
    plain = tmp_path / "plain"
    plain.mkdir()
    for p in range(4):
        tiny_trajectory("L", patient=p, site="B").save(plain / f"P{p:04d}_L.npz")
    unbounded = _setup(TrajectoryDataModule, [plain])  # fine without bounds
    assert unbounded.train[0].conditions() is None
    with pytest.raises(ValueError, match=r"plain/P000\d_L\.npz: metadata field 'simulation'"):
        _setup(TrajectoryDataModule, [plain], train_conditions=BOUNDS)


def test_caches_record_the_conditions_and_older_ones_are_rebuilt(views):
    dm = MeshGraphDataModule(str(views[1]))
    dm.prepare_data()
    source = dm.sources()[5]  # P0002_R
    meta = json.loads(source.stem.with_suffix(".json").read_text())
    assert meta["conditions"] == {
        "young_fat": 1100.0,
        "young_gland": 2500.0,
        "young_muscle": 6000.0,
        "young_skin": 1000.0,
        "friction": 0.25,
        "view": "mlo",
        "angle": mlo_angle(2),
    }
    del meta["conditions"]  # a cache written before the conditions were recorded
    source.stem.with_suffix(".json").write_text(json.dumps(meta))
    assert not cache_is_current(source.path, source.stem, dm.cache_last)
    dm.prepare_data()
    assert dm.breasts()[5].conditions()["angle"] == mlo_angle(2)


def _run_folder(folder: Path, data: dict) -> Path:
    (folder / ".hydra").mkdir(parents=True)
    config = {
        "cohort": {"out_dir": str(data.pop("cohort"))},
        "data": {"step": "compression", "n_folds": 4, **data},
        "model": {"_target_": "mammo_net.module.MeshGraphModule"},
    }
    OmegaConf.save(config, folder / ".hydra" / "config.yaml")
    return folder


def test_from_run_reads_a_list_of_folders(views, tmp_path):
    data_dir = ["${cohort.out_dir}/trajectories", "${cohort.out_dir}/trajectories_mlo"]
    run = _run_folder(
        tmp_path / "run",
        {"cohort": views[0].parent, "data_dir": data_dir, "fold": 1, "train_conditions": BOUNDS},
    )
    dm = MeshGraphDataModule.from_run(run)
    assert dm.data_dirs == views and dm.bounds == {"young_fat": (700.0, 2600.0)}
    assert dm.hparams.data_dir == [str(f) for f in views]
    for k, (data, message) in enumerate(
        [
            (
                {"data_dir": [1, 2]},
                r"field 'data\.data_dir' must be str or list of str, got \[1, 2\]",
            ),
            ({"data_dir": str(views[0]), "train_conditions": [1, 2]}, r"'data\.train_conditions'"),
            (
                {"data_dir": str(views[0]), "train_conditions": {"young_bone": [1, 2]}},
                r"data\.train_conditions\.young_bone: unknown",
            ),
        ]
    ):
        bad = _run_folder(tmp_path / f"bad{k}", {"cohort": tmp_path, **data})
        with pytest.raises(ValueError, match=rf"bad\d+/\.hydra/config\.yaml: .*{message}"):
            TrajectoryDataModule.from_run(bad)


def _benchmark():
    return benchmark_module("conditions_generalisation")


def test_benchmark_groups_held_out_and_in_range_breasts_by_view(views, tmp_path):
    """Two folds' predictions, each node off by (d, d, d) mm, so each breast's RMSE is d: 1 mm
    in range, 1.5 mm (cc) and 2 mm (mlo) held out."""
    folds = {0: [0, 1, 2], 1: [5, 6, 7]}  # the patients each fold predicts
    for fold, patients in folds.items():
        run = _run_folder(
            tmp_path / "runs" / f"fold{fold}",
            {"cohort": views[0].parent, "data_dir": [str(f) for f in views], "fold": fold,
             "train_conditions": BOUNDS},
        )  # fmt: skip
        predictions = {}
        for folder, view in zip(views, ("cc", "mlo"), strict=True):
            for p in patients:
                traj = tiny_trajectory("L")
                d = 1.0 if 700 <= FAT[p] <= 2600 else {"cc": 1.5, "mlo": 2.0}[view]
                predictions[f"P{p:04d}_L@{folder.name}"] = traj.compressed.transpose(1, 0, 2) + d
        (run / "predictions").mkdir()
        np.savez(run / "predictions" / "mesh_gnn.npz", **predictions)
    bench = _benchmark()
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=r"fold0/results\.md: not found: train\.py has not"):
        bench.evaluate([str(tmp_path / "runs" / "fold*")], None, None, out)
    for fold in folds:
        (tmp_path / "runs" / f"fold{fold}" / "results.md").write_text("finished\n")
    md, js = bench.evaluate([str(tmp_path / "runs" / "fold*")], None, None, out)
    report = json.loads(js.read_text())
    assert report["model"] == "mesh_gnn" and report["step"] == "compression"
    groups = {(g["view"], g["range"]): g for g in report["groups"]}
    assert groups["all", "all"]["n"] == 12
    assert groups["all", "held out"]["n"] == 6 and groups["cc", "in range"]["n"] == 3
    assert groups["cc", "held out"]["all_steps"]["mean"] == pytest.approx(1.5, rel=1e-5)
    assert groups["mlo", "held out"]["last_step"]["median"] == pytest.approx(2.0, rel=1e-5)
    assert groups["all", "in range"]["all_steps"]["std"] == pytest.approx(0.0, abs=1e-5)
    ratios = {r["view"]: r for r in report["ratios"]}
    assert ratios["all"]["all_steps"] == pytest.approx(1.75, rel=1e-5)
    assert ratios["mlo"]["last_step"] == pytest.approx(2.0, rel=1e-5)
    # every breast is the same tiny one: relative to its motion the ratio is the absolute one
    traj = tiny_trajectory("L")
    motion = np.sqrt(((traj.compressed[-1] - traj.unloaded[-1]) ** 2).sum(-1).mean())
    assert [r["motion"] for r in report["breasts"]] == pytest.approx([motion] * 12, rel=1e-6)
    assert ratios["mlo"]["last_step_relative"] == pytest.approx(2.0, rel=1e-5)
    text = md.read_text()
    assert "| cc | held out | 3 | (1.500, 1.500) +- 0.000 |" in text
    assert "| all | 1.75x | 1.75x | 1.75x |" in text
    assert "Worst ratio: 2.00x (target <= 1.25x: missed)." in text
    runs = {r["run"]: r for r in report["runs"]}
    fold0 = str(tmp_path / "runs" / "fold0")
    assert runs["all"]["last_step"] == pytest.approx(1.75, rel=1e-5)
    assert (runs[fold0]["in_range"], runs[fold0]["held_out"]) == (4, 2)
    assert runs[fold0]["all_steps"] == pytest.approx(1.75, rel=1e-5)
    assert "control_all_steps" not in runs["all"]
    # a control that scored fold 0's breasts only, 1.4x worse on its held-out ones
    control = tmp_path / "control.json"
    rows = [
        {
            **r,
            "all_steps": 1.4 if r["held_out"] else 1.0,
            "last_step": 2.8 if r["held_out"] else 2.0,
        }
        for r in report["breasts"]
        if r["run"] == fold0
    ]
    control.write_text(json.dumps({"breasts": rows}))
    md, js = bench.evaluate([str(tmp_path / "runs" / "fold*")], None, None, out, control)
    (entry, fold) = json.loads(js.read_text())["runs"]
    assert entry["run"] == "all" and fold["run"] == fold0 and entry["held_out"] == 2
    assert entry["control_last_step"] == pytest.approx(1.4, rel=1e-5)
    assert entry["controlled_all_steps"] == pytest.approx(1.25, rel=1e-5)
    assert "| all | 4 / 2 | 1.75x / 1.75x | 1.40x / 1.40x | 1.25x / 1.25x |" in md.read_text()
    control.write_text(json.dumps({"breasts": [{**rows[0], "breast": "P9999_L"}]}))
    with pytest.raises(ValueError, match="--control: it scored none of these breasts"):
        bench.evaluate([str(tmp_path / "runs" / "fold*")], None, None, out, control)
    control.write_text(json.dumps({"groups": []}))
    with pytest.raises(ValueError, match=r"control\.json: not a conditions_generalisation JSON"):
        bench.evaluate([str(tmp_path / "runs" / "fold*")], None, None, out, control)
    # other bounds given: every breast in range, no ratio
    _, js = bench.evaluate(
        [str(tmp_path / "runs" / "fold*")], "mesh_gnn", {"friction": (0.0, 1.0)}, out
    )
    assert json.loads(js.read_text())["ratios"][0]["all_steps"] is None
    # bad input names the file
    with pytest.raises(ValueError, match=r"fold0/predictions/xgboost\.npz: not found"):
        bench.evaluate([str(tmp_path / "runs" / "fold0")], "xgboost", None, out)
    with pytest.raises(SystemExit, match=r"--bounds: .*young_bone"):
        bench.main([str(tmp_path / "runs" / "fold0"), "--bounds", '{"young_bone": [1, 2]}'])


def test_stiffness_range_is_recorded_in_a_checkpoint_trained_without_it(views, tmp_path):
    """`mammo_net.stiffness_range` on a graph model of the unloaded state trained before the
    setting: the checkpoint then loads with the range of its training breasts' moduli (fat
    800-2500 Pa of the bounds' patients in fold 1's training split), the weights unchanged
    and the stale predictions removed; a second call and a model without the gain refuse."""
    run = _run_folder(
        tmp_path / "run",
        {"cohort": views[0].parent, "data_dir": [str(f) for f in views], "fold": 1,
         "step": "unloaded", "train_conditions": BOUNDS},
    )  # fmt: skip
    old = MeshGraphModule("unloaded", hidden=8, layers=1, slices=2, heads=2, decoder_hidden=8,
                          stiffness_range=False)  # fmt: skip
    hparams = {k: v for k, v in old.hparams.items() if k != "stiffness_range"}
    (run / "checkpoints").mkdir()
    checkpoint = {"network": "mesh_gnn", "hyper_parameters": hparams}
    torch.save({**checkpoint, "state_dict": old.state_dict()}, run / "checkpoints" / "best.ckpt")
    (run / "predictions").mkdir()
    (run / "predictions" / "mesh_gnn.npz").write_bytes(b"stale")
    (run / "predictions" / "mesh_gnn.json").write_text("{}")
    assert not NetworkModule.from_checkpoint(run / "checkpoints" / "best.ckpt").net.bounded

    bounds = record_stiffness_range(run)
    model = NetworkModule.from_checkpoint(run / "checkpoints" / "best.ckpt")
    assert model.hparams.stiffness_range and model.net.bounded
    torch.testing.assert_close(model.net.condition_bounds, bounds)
    dm = MeshGraphDataModule.from_run(run)
    dm.prepare_data()
    dm.setup()
    fat = sorted({b.conditions()["young_fat"] for b in dm.train})
    assert 550.0 not in fat and 3000.0 not in fat  # the bounds hold them out
    np.testing.assert_allclose(bounds[:, 0], np.log(np.array(fat)[[0, -1]] / 1100.0), rtol=1e-6)
    assert bounds[0, 4:].eq(-np.inf).all() and bounds[1, 4:].eq(np.inf).all()  # not moduli
    for name, weights in old.state_dict().items():
        torch.testing.assert_close(model.state_dict()[name], weights)
    assert not (run / "predictions" / "mesh_gnn.npz").exists()
    assert (run / "predictions" / "mesh_gnn.json").exists()
    with pytest.raises(ValueError, match=r"best\.ckpt: records its stiffness range already"):
        record_stiffness_range(run)
    plain = MeshGraphModule("unloaded", hidden=8, layers=1, slices=2, heads=2, decoder_hidden=8,
                            compliance_scaling=False)  # fmt: skip
    torch.save({**checkpoint, "hyper_parameters": dict(plain.hparams),
                "state_dict": plain.state_dict()}, run / "checkpoints" / "best.ckpt")  # fmt: skip
    with pytest.raises(ValueError, match=r"best\.ckpt: not a graph model with the compliance"):
        record_stiffness_range(run)
