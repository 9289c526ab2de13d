"""The evaluation report on a tiny cohort, against numbers computed by hand."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_trajectory
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import mammo_net.module  # noqa: F401  (stores model/att_blstm_signature, as train.py's import does)
from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from mammo_net import evaluation as ev
from mammo_net.metrics import node_rmse
from mammo_net.report import write_report
from mammo_net.report_data import collect
from mammo_net.validity import ValidityProjection

CONF = Path(__file__).resolve().parents[1] / "conf"

# Three compressed breasts (5 nodes, 3 recorded steps at compression ratios 0.1, 0.2, 0.3;
# node 3 is fat and skin, node 4 muscle, nodes 0-2 interfaces; node 0 is skin too). Each is
# predicted with an offset (d, d, d) per node and step, whose node RMSE is d:
#   A: d = 2 at the skin nodes 0 and 3, 1 elsewhere      -> all steps 1.4, last step 1.4
#   B: d = 3                                              -> 3, 3
#   C: d = 1, 2, 3 at steps 1, 2, 3                       -> 2, 3
OFFSETS = {
    "P0000_L": np.array([2, 1, 1, 2, 1.0])[:, None] * np.ones(3),
    "P0001_L": np.full((5, 3), 3.0),
    "P0002_L": np.ones((5, 1)) * [1.0, 2.0, 3.0],
}
VOLUMES = {"P0000_L": 100.0, "P0001_L": 300.0, "P0002_L": 200.0}
FE_SECONDS = {"P0000_L": 10.0, "P0001_L": 20.0, "P0002_L": 30.0}
PREDICT_SECONDS = {"P0000_L": 0.01, "P0001_L": 0.02, "P0002_L": 0.03}


def _run(folder: Path, data_dir: Path, step: str, fold, predictions: dict, seconds=None) -> Path:
    (folder / ".hydra").mkdir(parents=True)
    data = {"step": step, "data_dir": str(data_dir), "split": None, "fold": fold, "n_folds": 10}
    OmegaConf.save({"data": data}, folder / ".hydra" / "config.yaml")
    (folder / "predictions").mkdir()
    np.savez(folder / "predictions" / "model.npz", **predictions)
    if seconds is not None:
        timing = {"seconds": seconds, "machine": {}}
        (folder / "predictions" / "model.json").write_text(json.dumps(timing))
    return folder


@pytest.fixture
def cohort(tmp_path):
    """Trajectories, two cross-validation folds (A, B | C) and a one-fold unloaded run."""
    data = tmp_path / "trajectories"
    data.mkdir()
    truth = {}
    for p, name in enumerate(OFFSETS):
        t = tiny_trajectory("L", patient=p, breast_volume_cm3=VOLUMES[name])
        t.metadata["simulation"] = {"seconds": {"compression": FE_SECONDS[name], "unloaded": 1.0}}
        t.save(data / f"{name}.npz")
        truth[name] = t
    compressed = {
        n: (t.compressed.transpose(1, 0, 2) + OFFSETS[n][:, :, None]).astype(np.float32)
        for n, t in truth.items()
    }
    names = list(OFFSETS)
    runs = tmp_path / "runs"
    _run(runs / "fold0", data, "compression", 0,
         {n: compressed[n] for n in names[:2]}, {n: PREDICT_SECONDS[n] for n in names[:2]})  # fmt: skip
    _run(runs / "fold1", data, "compression", 1,
         {n: compressed[n] for n in names[2:]}, {n: PREDICT_SECONDS[n] for n in names[2:]})  # fmt: skip
    unloaded = {
        n: (t.unloaded.transpose(1, 0, 2) + 0.5).astype(np.float32) for n, t in truth.items()
    }
    _run(runs / "one_fold", data, "unloaded", None, unloaded)
    return runs


def _report(runs: Path, out: Path):
    analysis = OmegaConf.load(CONF / "analysis" / "default.yaml")
    write_report([runs / "*"], out, analysis)
    return json.loads((out / "report.json").read_text())


def test_report_numbers_match_hand_computed(cohort, tmp_path):
    numbers = _report(cohort, tmp_path / "report")
    cv = numbers["summary"]["10_fold_CV_compression"]["model"]
    # Per breast, all steps [1.4, 3, 2]; last step [1.4, 3, 3].
    assert cv["n_breasts"] == 3
    assert cv["all_steps_mean"] == pytest.approx(6.4 / 3)
    assert cv["all_steps_median"] == pytest.approx(2.0)
    assert cv["all_steps_std"] == pytest.approx(np.sqrt(1.3066667 / 3))
    assert cv["last_step_mean"] == pytest.approx(7.4 / 3)
    assert cv["last_step_median"] == pytest.approx(3.0)
    # Skin nodes 0 and 3: A 2, B 3, C 2 (all steps) and 2, 3, 3 (last step).
    assert cv["surface_all_steps_mean"] == pytest.approx(7 / 3)
    assert cv["surface_last_step_mean"] == pytest.approx(8 / 3)
    # Tissue: fat is node 3 only (A 2, B 3, C 2), muscle node 4 only (1, 3, 2), no pure gland.
    assert cv["fat_nodes"] == 3 and cv["muscle_nodes"] == 3 and cv["gland_nodes"] == 0
    assert cv["fat_mean"] == pytest.approx(7 / 3)
    assert cv["fat_std"] == pytest.approx(np.sqrt(2 / 9))
    assert cv["fat_mu"] == pytest.approx((2 * np.log(2) + np.log(3)) / 3)
    assert cv["muscle_mean"] == pytest.approx(2.0)
    assert np.isnan(cv["gland_mean"])
    # At 20 % compression (the second step): A 1.4, B 3, C 2.
    assert cv["at_ratio_mean"] == pytest.approx(6.4 / 3)
    assert cv["at_ratio_median"] == pytest.approx(2.0)
    assert cv["node_step_max"] == pytest.approx(3.0)
    # Volume 100, 300, 200 cm^3 against RMSE 1.4, 3, 2: r = 160 / sqrt(20000 * 1.30667).
    r = numbers["volume_pearson_r"]["10_fold_CV_compression"]["model"]
    assert r == pytest.approx(160 / np.sqrt(20000 * 1.3066667))
    # FE: median 20 s; prediction: median 0.02 s.
    assert numbers["timing"]["10_fold_CV_compression"] == pytest.approx(20.0)
    assert cv["predict_seconds_median"] == pytest.approx(0.02)
    unloaded = numbers["summary"]["one_fold_unloaded"]["model"]
    assert unloaded["all_steps_mean"] == pytest.approx(0.5)
    assert unloaded["last_step_std"] == pytest.approx(0.0, abs=1e-6)
    assert "predict_seconds_median" not in unloaded  # no timing file saved

    text = (tmp_path / "report" / "report.md").read_text()
    assert (
        "| 10-fold CV | compression | model | 3 | (2.13, 2.00) +- 0.66 | (2.47, 3.00) +- 0.75 |"
        in text
    )
    assert (
        "| one-fold | unloaded | model | 3 | (0.50, 0.50) +- 0.00 | (0.50, 0.50) +- 0.00 |" in text
    )
    assert "| 20.0 | 0.0200 | 1,000x |" in text
    assert "No split has two models to compare." in text  # one model per split here
    rows = (tmp_path / "report" / "per_breast.csv").read_text().splitlines()
    assert len(rows) == 1 + 6 and "10-fold CV,compression,model,P0001_L,3.0000" in rows[2]
    steps = (tmp_path / "report" / "per_step.csv").read_text().splitlines()
    assert "10-fold CV,compression,model,2,2.1333" in steps[2]  # step 2: mean(1.4, 3, 2)
    figures = {p.name for p in (tmp_path / "report" / "figures").glob("*.png")}
    assert {
        "error_classes_compression.png",
        "error_classes_unloaded.png",
        "10_fold_CV_compression_compression_ratio.png",
        "10_fold_CV_compression_tissue.png",
        "10_fold_CV_compression_volume.png",
        "10_fold_CV_compression_per_step.png",
        "10_fold_CV_compression_sections_best.png",
        "10_fold_CV_compression_sections_worst.png",
        "one_fold_unloaded_sections_worst.png",
    } <= figures


def test_error_classes_of_the_tiny_cohort(cohort):
    (e,) = [e for e in collect([cohort / "*"]) if e.step == "compression"]
    nodes = np.concatenate([v.mean(1) for v in e.models["model"].errors.values()])
    # 15 node errors: three at 1 mm (class 0-2), twelve at 2 or 3 mm (class 2-4).
    np.testing.assert_allclose(ev.error_classes(nodes)[:3], [20.0, 80.0, 0.0], atol=1e-4)


def test_common_breasts_pair_the_models(cohort, tmp_path):
    other = dict(np.load(cohort / "fold0" / "predictions" / "model.npz"))
    np.savez(cohort / "fold0" / "predictions" / "second.npz", **other)  # fold 0 only: A, B
    analysis = OmegaConf.load(CONF / "analysis" / "default.yaml")
    analysis.sections = False
    write_report([cohort / "*"], tmp_path / "all", analysis)
    analysis.common_breasts = True
    write_report([cohort / "*"], tmp_path / "common", analysis)
    for folder, n in (("all", 3), ("common", 2)):
        s = json.loads((tmp_path / folder / "report.json").read_text())["summary"]
        assert s["10_fold_CV_compression"]["model"]["n_breasts"] == n
        assert s["10_fold_CV_compression"]["second"]["n_breasts"] == 2


def test_paired_comparison_of_two_models(cohort, tmp_path):
    """A second model with error 2 mm everywhere on fold 0's breasts A and B: the first model's
    per-breast RMSE (1.4, 3) minus (2, 2) -> differences (-0.6, +1), both steps alike."""
    model = dict(np.load(cohort / "fold0" / "predictions" / "model.npz"))
    second = {n: v - OFFSETS[n][:, :, None] + 2.0 for n, v in model.items()}
    np.savez(cohort / "fold0" / "predictions" / "second.npz", **second)
    analysis = OmegaConf.load(CONF / "analysis" / "default.yaml")
    analysis.sections = False
    write_report([cohort / "*"], tmp_path / "report", analysis)
    paired = json.loads((tmp_path / "report" / "report.json").read_text())["paired"]
    assert paired["one_fold_unloaded"] == {}
    half = 12.7062 * np.std([-0.6, 1.0], ddof=1) / np.sqrt(2)  # t(0.975, 1 dof) sd / sqrt(n)
    for key in ("all_steps", "last_step"):
        d = paired["10_fold_CV_compression"]["model - second"][key]
        assert d["n"] == 2
        np.testing.assert_allclose(
            [d["mean_diff"], d["ci95_low"], d["ci95_high"], d["relative"], d["a_better"]],
            [0.2, 0.2 - half, 0.2 + half, 0.1, 0.5],
            atol=1e-3,
        )
        assert d["wilcoxon_p"] == pytest.approx(1.0)  # n = 2: every sign pattern as extreme
    text = (tmp_path / "report" / "report.md").read_text()
    assert "| 10-fold CV | compression | model - second | 2 | +0.20 [" in text


def test_paired_difference_errors_and_degenerate_cases():
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        ev.paired_difference([1.0, 2.0], [1.0])
    same = ev.paired_difference([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    assert same["mean_diff"] == 0 and np.isnan(same["wilcoxon_p"]) and same["a_better"] == 0


def test_report_refuses_a_breast_predicted_twice(cohort):
    second = cohort / "fold1" / "predictions" / "model.npz"
    a = dict(np.load(cohort / "fold0" / "predictions" / "model.npz"))
    np.savez(second, **a)
    with pytest.raises(
        ValueError, match=r"fold1/predictions/model.npz: breast P0000_L was already"
    ):
        collect([cohort / "*"])


def test_report_names_file_and_field_of_a_wrong_shape(cohort):
    path = cohort / "fold1" / "predictions" / "model.npz"
    np.savez(path, P0002_L=np.zeros((5, 2, 3), np.float32))
    with pytest.raises(ValueError, match=r"model.npz: field 'P0002_L' has shape \(5, 2, 3\)"):
        collect([cohort / "*"])


def test_excluded_runs_are_left_out(cohort):
    (e,) = [
        e for e in collect([cohort / "*"], exclude=[cohort / "fold1"]) if e.step == "compression"
    ]
    assert sorted(e.models["model"].errors) == ["P0000_L", "P0001_L"]  # fold 0's breasts only
    assert [e.step for e in collect([cohort / "*"], exclude=[cohort / "fold*"])] == ["unloaded"]
    with pytest.raises(
        FileNotFoundError, match=r"no run folder matches .*\(exclude: \[.*runs/\*.\]\)"
    ):
        collect([cohort / "fold*"], exclude=[cohort / "*"])


def test_report_needs_run_folders(tmp_path):
    with pytest.raises(FileNotFoundError, match="no run folder matches"):
        collect([tmp_path / "nothing*"])
    (tmp_path / "run").mkdir()
    with pytest.raises(FileNotFoundError, match=r"config.yaml: not found"):
        collect([tmp_path / "run"])


def test_exp2_and_line_fits_recover_exact_curves():
    x = np.linspace(0.01, 0.7, 40)
    y = ev.exp2(x, 1.0, 0.5, 0.01, 8.0)
    p, r2 = ev.fit_exp2(x, y)
    assert r2 == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(ev.exp2(x, *p), y, rtol=1e-5)
    line, r2 = ev.fit_line(x, 2 * x + 1)
    np.testing.assert_allclose(line, [2, 1])
    assert r2 == pytest.approx(1.0)
    assert np.isnan(ev.fit_exp2(x[:4], y[:4])[1])  # too few bins


def test_binning_interpolation_and_lognormal():
    centres, means, counts = ev.binned_means([0.001, 0.009, 0.015, 0.2], [1, 3, 5, 7], 0.01)
    np.testing.assert_allclose(centres, [0.005, 0.015, 0.205])
    np.testing.assert_allclose(means, [2, 5, 7])
    np.testing.assert_array_equal(counts, [2, 1, 1])
    assert ev.value_at([0.1, 0.3], [1.0, 3.0], 0.2) == pytest.approx(2.0)
    assert np.isnan(ev.value_at([0.1, 0.3], [1.0, 3.0], 0.35))
    rng = np.random.default_rng(0)
    mu, sigma = ev.lognormal_fit(rng.lognormal(0.4, 0.6, 200_000))
    assert mu == pytest.approx(0.4, abs=0.01) and sigma == pytest.approx(0.6, abs=0.01)
    grid = np.linspace(1e-4, 60, 200_001)
    assert np.trapezoid(ev.lognormal_pdf(grid, 0.4, 0.6), grid) == pytest.approx(1.0, abs=1e-4)
    assert ev.error_class_labels()[0] == "0-2" and ev.error_class_labels()[-1] == "> 22"
    np.testing.assert_allclose(ev.error_classes([0.0, 21.9, 22.0, 50.0])[[0, 10, 11]], [25, 25, 50])
    assert ev.pearson_r([1, 2, 3], [2, 4, 6]) == pytest.approx(1.0)
    assert np.isnan(ev.pearson_r([1, 1, 1], [2, 4, 6]))


def test_report_command_config_composes(cohort, tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("report", overrides=[f"runs=[{cohort}/*]", f"out_dir={tmp_path / 'r'}"])
    assert cfg.runs == [f"{cohort}/*"] and cfg.data_dir is None
    assert cfg.exclude == []  # every committed fold is on the current cohort (docs/results.md)
    assert cfg.analysis.linear_fit_max_ratio == 0.53 and cfg.analysis.ratio_of_interest == 0.2
    assert cfg.projection.min_volume_ratio == 0.05  # scored as predict.py writes them
    out = write_report(cfg.runs, cfg.out_dir, cfg.analysis, cfg.data_dir, cfg.exclude)
    assert (out / "report.md").exists()
    for command in ("report", "predict", "train"):  # one projection group, raw on request
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            default, raw = compose(command), compose(command, overrides=["projection=raw"])
        assert default.projection == cfg.projection and not raw.get("projection")


def test_report_scores_the_projected_predictions(cohort, tmp_path):
    """With a projection the report scores what predict.py writes: each prediction projected
    (`ValidityProjection.project_step`), and says so."""
    projection = ValidityProjection()
    (raw,) = [e for e in collect([cohort / "fold*"]) if e.step == "compression"]
    (e,) = [e for e in collect([cohort / "fold*"], projection=projection)]
    moved = 0
    for fold in ("fold0", "fold1"):
        for name, predicted in np.load(cohort / fold / "predictions" / "model.npz").items():
            traj = Trajectory.load(cohort.parent / "trajectories" / f"{name}.npz")
            steps = projection.project_step(traj, "compression", predicted.transpose(1, 0, 2))
            assert (signed_volume(steps.astype(np.float64), traj.cells) > 0).all()
            expected = node_rmse(steps.transpose(1, 0, 2), e.truth[name].positions)
            np.testing.assert_allclose(e.models["model"].errors[name], expected, rtol=1e-5)
            moved += not np.allclose(expected, raw.models["model"].errors[name])
    assert moved  # the offsets push skin into the plates: the projection changes the scores
    analysis = OmegaConf.load(CONF / "analysis" / "default.yaml")
    write_report([cohort / "fold*"], tmp_path / "r", analysis, projection=projection)
    numbers = json.loads((tmp_path / "r" / "report.json").read_text())
    assert numbers["projection"] == {"min_volume_ratio": 0.05, "volume_tolerance": 0.01}
    assert "after the validity projection" in (tmp_path / "r" / "report.md").read_text()
