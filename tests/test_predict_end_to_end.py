"""predict.py end to end: fresh phantoms meshed and simulated (a tiny cohort), XGBoost fitted
for both steps on all but one patient, then the held-out patient's mesh file (no FE result in
it) through predict.py: deformed VTU files and mapped landmarks, and the predicted final
shape compared with the FE's."""

import csv
import json

import meshio
import numpy as np
import pytest
from test_cohort import TINY, _cfg
from test_predictor import _predict_cfg

import predict
from datamodules.trajectories import TrajectoryDataModule
from fem.cohort import run_cohort
from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from mammo_net import baselines
from mammo_net.validity import PhysicallyImpossible

FEW_STEPS = ("simulation.unloaded_steps=5", "simulation.compression_steps=6")


@pytest.fixture(scope="module")
def tiny_cohort(tmp_path_factory):
    """5 patients (10 breasts, 500-900 tetrahedra) and XGBoost models of both steps fitted on
    the breasts of the patients outside fold 0 of 5."""
    out = tmp_path_factory.mktemp("cohort")
    report = run_cohort(_cfg(out, "n_patients=5", "simulate=true", *TINY, *FEW_STEPS))
    assert report["simulation"]["n_failed"] == 0
    models = {}
    for step in ("unloaded", "compression"):
        dm = TrajectoryDataModule(str(out / "trajectories"), step=step, fold=0, n_folds=5)
        dm.prepare_data()
        dm.setup()
        X, Y = baselines.stack_rows(dm.rows(dm.train))
        booster = baselines.fit_xgboost(X, Y, n_estimators=60, max_depth=5, n_jobs=2)
        models[step] = baselines.save_xgboost(booster, out / f"{step}.json", dm.schema())
    return out, models, [b.name for b in dm.val]


def test_a_new_breast_through_predict_py(tiny_cohort, tmp_path):
    out, models, held_out = tiny_cohort
    name = held_out[0]
    fe = Trajectory.load(out / "trajectories" / f"{name}.npz")
    thickness = float(fe.metadata["simulation"]["compressed_thickness_mm"])
    inside = fe.points[fe.cells[len(fe.cells) // 2]].mean(0)  # a "lesion": an element centroid
    (tmp_path / "lesion.csv").write_text("name,x,y,z\nlesion,{},{},{}\n".format(*inside))
    cfg = _predict_cfg(
        tmp_path, tmp_path, f"input={out / f'{name}.vtu'}", f"thickness={thickness}",
        f"laterality={fe.metadata['laterality']}", f"landmarks={tmp_path / 'lesion.csv'}",
        f"unloaded_model={models['unloaded']}", f"compression_model={models['compression']}",
    )  # fmt: skip
    result = predict.predict(cfg)
    final = meshio.read(result / f"compressed_{thickness:g}mm.vtu").points
    unloaded = meshio.read(result / "unloaded.vtu").points
    assert final.shape == fe.compressed[-1].shape

    def rms(a, b):
        return float(np.sqrt(((a - b) ** 2).sum(1).mean()))

    # Stated tolerance, on a patient the models never saw: the final shape within 55 % of
    # the FE displacement (RMS over nodes) of the FE's final shape (measured with the sliding
    # chest wall: 3.9 mm of 8.5 mm, 46 %; the first engine's chest wall let the breast slide
    # down the wall, 23.2 mm), the unloaded shape within 3 mm RMS of the FE's.
    error = rms(final, fe.compressed[-1])
    assert error < 0.55 * rms(fe.compressed[-1], fe.points)
    assert rms(unloaded, fe.unloaded[-1]) < 3.0
    # The predicted shape is about as thick as the FE's over the plates (mm; the held muscle
    # and the tissue behind the plates' chest-side edge stick out above and below them).
    over = fe.compressed[-1][:, 1] > fe.plates[-1, 0, 0, 1]
    assert np.ptp(final[over, 2]) == pytest.approx(np.ptp(fe.compressed[-1][over, 2]), abs=6.0)
    with open(result / "landmarks.csv") as f:
        (row,) = list(csv.DictReader(f))
    cell = fe.cells[len(fe.cells) // 2]
    np.testing.assert_allclose(
        [float(row[f"compressed_{c}"]) for c in "xyz"], final[cell].mean(0), atol=2e-3
    )
    np.testing.assert_allclose(
        [float(row[f"unloaded_{c}"]) for c in "xyz"], unloaded[cell].mean(0), atol=2e-3
    )
    # The mapped lesion lies near where the FE moves the same material point (measured: 6.1
    # mm from it).
    lesion = np.array([float(row[f"compressed_{c}"]) for c in "xyz"])
    assert np.linalg.norm(lesion - fe.compressed[-1][cell].mean(0)) < 3 * error
    # checks.json records what the written meshes are: the trees' shapes, projected onto
    # valid ones (the trees alone invert elements here)
    record = json.loads((result / "checks.json").read_text())["checks"]
    checks = record["shapes"]
    assert set(checks) == {"unloaded", f"compressed_{thickness:g}mm"}
    inverted = int((signed_volume(final, fe.cells) <= 0).sum())
    assert checks[f"compressed_{thickness:g}mm"]["inverted_elements"] == inverted == 0
    assert record["projection"]["steps_moved"] > 0 and record["projection"]["moved_max_mm"] > 0
    change = signed_volume(final, fe.cells).sum() / signed_volume(unloaded, fe.cells).sum() - 1
    assert checks[f"compressed_{thickness:g}mm"]["volume_change"] == pytest.approx(change, abs=1e-4)


def test_physical_checks_refuse_before_writing(tiny_cohort, tmp_path):
    """With checks.on_violation=refuse, a shape outside the tolerances (here: any volume
    change at all) stops predict.py before its first output file."""
    out, models, held_out = tiny_cohort
    cfg = _predict_cfg(
        tmp_path, tmp_path, f"input={out / f'{held_out[0]}.vtu'}", "thickness=40", "laterality=L",
        f"unloaded_model={models['unloaded']}", f"compression_model={models['compression']}",
        "checks.max_volume_change=0", "checks.on_violation=refuse",
    )  # fmt: skip
    with pytest.raises(
        PhysicallyImpossible, match=r"volume changed by .* \(checks.max_volume_change: 0 %\)"
    ):
        predict.predict(cfg)
    assert not (tmp_path / "out").exists()  # nothing written, not even the folder
