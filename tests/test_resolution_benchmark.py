"""The resolution benchmark's table (benchmarks/resolution_generalisation.py) on made-up rows:
ratios to the native resolution, the verdict and the projection's columns."""

import pytest
from conftest import benchmark_module


def _row(breast: str, resolution: str, error: float, projected: bool) -> dict:
    step = {"all_steps": error / 2, "last_step": error, "inverted": 3, "element_steps": 100}
    if projected:
        step["projected"] = {"all_steps": error / 2, "last_step": error + 0.1, "inverted": 0,
                             "seconds": 0.2}  # fmt: skip
    return {
        "breast": breast,
        "resolution": resolution,
        "tetrahedra": {"native": 2000, "2x": 4000}[resolution],
        "fe_s": 1.0,
        "predict_s": 0.05,
        "compression": dict(step),
        "unloaded": dict(step),
    }


@pytest.mark.parametrize("projected", [False, True])
def test_summary_ratios_verdict_and_projection(projected):
    bench = benchmark_module("resolution_generalisation")
    rows = [
        _row("P0000_L", "native", 1.0, projected),
        _row("P0001_R", "native", 2.0, projected),
        _row("P0000_L", "2x", 1.2, projected),
        _row("P0001_R", "2x", 2.7, projected),  # mean 1.95 against 1.5: 1.30x
    ]
    table = bench.summary(rows, ["native", "2x"])
    assert table[0]["compression_last_step_ratio"] == pytest.approx(1.0)
    assert table[1]["compression_last_step_ratio"] == pytest.approx(1.3)
    assert table[1]["unloaded_all_steps_mm"] == pytest.approx(0.975)
    assert table[1]["compression_inverted"] == 6 and table[1]["compression_element_steps"] == 200
    text = bench.markdown(table)
    assert "Worst ratio to native: 1.30x (target <= 1.25x: missed)." in text
    assert ("after the validity projection" in text) is projected
    if projected:
        assert table[1]["compression_projected_last_step_mm"] == pytest.approx(2.05)
        assert table[1]["unloaded_projected_inverted"] == 0
        assert "| 2x | 2.050 / 2.050 mm | 0 / 0 | 0.20 / 0.20 |" in text
    rows[3]["compression"]["last_step"] = rows[3]["unloaded"]["last_step"] = 2.0
    rows[3]["compression"]["all_steps"] = rows[3]["unloaded"]["all_steps"] = 1.0
    assert "1.07x (target <= 1.25x: met)" in bench.markdown(bench.summary(rows, ["native", "2x"]))


def test_models_default_to_the_split_fold_and_another_split_is_refused():
    """Evaluating fold 1's validation breasts with fold 0's model would score breasts it was
    trained on: the default model is the split's own fold, and another split's is refused."""
    bench = benchmark_module("resolution_generalisation")
    split = {"split": "k_fold", "fold": 1, "n_folds": 10, "val_fraction": 0.1, "seed": 0}
    path = bench.model_path(None, "compression", split)
    assert path == bench.RUNS / "compression" / "fold1" / "checkpoints" / "best.ckpt"
    fold0 = bench.RUNS / "unloaded" / "fold0" / "checkpoints" / "best.ckpt"
    with pytest.raises(
        SystemExit, match=r"fold0/checkpoints/best\.ckpt: trained on the split .*'fold': 0"
    ):
        bench.model_path(fold0, "unloaded", split)
    one_fold = {**split, "split": "one_fold", "fold": None}
    with pytest.raises(SystemExit, match=r"--compression: the committed models are k-fold"):
        bench.model_path(None, "compression", one_fold)


def test_pooled_rows_join_folds_and_refuse_a_breast_scored_twice(tmp_path):
    """``--pool``: several folds' files make one set of rows, only breasts scored at every
    asked resolution; a breast in two files or a file without rows is refused by name."""
    bench = benchmark_module("resolution_generalisation")
    fold0 = [_row("P0000_L", r, 1.0, True) for r in ("native", "2x")]
    fold1 = [_row("P0001_R", "native", 2.0, False)]  # not scored at 2x: left out
    fold1 += [_row("P0002_L", r, 3.0, False) for r in ("native", "2x")]
    files = [tmp_path / "fold0.json", tmp_path / "fold1.json"]
    for path, rows in zip(files, (fold0, fold1), strict=True):
        bench.write_report(path, {"out": path}, bench.summary(rows, ["native"]), [], rows)
    rows = bench.pooled_rows(files, ["native", "2x"])
    assert sorted({r["breast"] for r in rows}) == ["P0000_L", "P0002_L"] and len(rows) == 4
    assert bench.summary(rows, ["native", "2x"])[0]["compression_last_step_mm"] == 2.0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # atomic
    with pytest.raises(SystemExit, match=r"fold0\.json: breast P0000_L is also scored in .*fold0"):
        bench.pooled_rows([files[0], files[0]], ["native", "2x"])
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit, match=r"bad\.json: not a resolution benchmark's --out file"):
        bench.pooled_rows([tmp_path / "bad.json"], ["native"])
