"""Tree baselines: the array forest predicts exactly as scikit-learn; both models reload from
their non-pickle files and predict identical values."""

import numpy as np
import pytest
from sklearn.ensemble import ExtraTreesRegressor

from datamodules.features import REVISIONS, FeatureSchema
from mammo_net.baselines import (
    fit_ert,
    fit_xgboost,
    forest_arrays,
    forest_schema,
    load_forest,
    load_xgboost,
    predict_xgboost,
    save_forest,
    save_xgboost,
    stack_rows,
    xgboost_schema,
)


def data(n=400, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 5)).astype(np.float32)
    Y = np.stack([X[:, 0] * 2, np.sin(X[:, 1]), X[:, 2] * X[:, 3]], 1).astype(np.float32)
    return X, Y


def test_forest_arrays_predict_like_scikit_learn():
    X, Y = data()
    model = ExtraTreesRegressor(n_estimators=7, random_state=0).fit(X, Y)
    forest = forest_arrays(model)
    Xt, _ = data(100, seed=1)
    np.testing.assert_allclose(forest.predict(Xt), model.predict(Xt), rtol=1e-6, atol=1e-6)


def test_compiled_forest_predicts_as_the_reference():
    X, Y = data(2000)
    forest = fit_ert(X, Y, n_estimators=9, min_samples_leaf=3, n_jobs=1)
    Xt, _ = data(500, seed=2)
    for threads in (1, 2, 4):
        np.testing.assert_array_equal(forest.compiled(5, threads)(Xt), forest.predict(Xt))
    stump = fit_ert(X[:1], Y[:1], n_estimators=2, n_jobs=1)  # single-leaf trees
    np.testing.assert_array_equal(stump.compiled(5)(Xt), stump.predict(Xt))


def test_baselines_reload_identically(tmp_path):
    X, Y = data()
    forest = fit_ert(X, Y, n_estimators=5, n_jobs=1)
    again = load_forest(save_forest(forest, tmp_path / "ert.npz"))
    np.testing.assert_array_equal(again.predict(X), forest.predict(X))
    booster = fit_xgboost(X, Y, n_estimators=10, max_depth=3, n_jobs=1)
    loaded = load_xgboost(save_xgboost(booster, tmp_path / "xgb.json"))
    np.testing.assert_array_equal(predict_xgboost(loaded, X), predict_xgboost(booster, X))
    assert (tmp_path / "xgb.json").read_text().startswith("{")  # JSON, not a pickle
    fit = np.sqrt(((predict_xgboost(booster, X) - Y) ** 2).mean())
    assert fit < 0.6 * np.sqrt(((Y - Y.mean(0)) ** 2).mean())  # it learned something
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ert.npz", "xgb.json"]


def test_stack_rows():
    blocks = [(np.ones((4, 2)), np.zeros((4, 3))), (2 * np.ones((3, 2)), np.ones((3, 3)))]
    X, Y = stack_rows(iter(blocks))
    assert X.shape == (7, 2) and Y.shape == (7, 3) and X.dtype == np.float32
    np.testing.assert_array_equal(X[4:], 2)


def test_model_files_carry_their_feature_schema(tmp_path):
    X, Y = data()
    schema = FeatureSchema.of("unloaded", 100)
    forest = fit_ert(X, Y, n_estimators=2, n_jobs=1)
    assert forest_schema(save_forest(forest, tmp_path / "ert.npz", schema)) == schema
    assert forest_schema(save_forest(forest, tmp_path / "old.npz")) is None
    booster = fit_xgboost(X, Y, n_estimators=2, max_depth=2, n_jobs=1)
    for suffix in (".json", ".ubj"):
        loaded = load_xgboost(save_xgboost(booster, tmp_path / f"xgb{suffix}", schema))
        assert xgboost_schema(loaded) == schema
    schema.check("unloaded")
    with pytest.raises(ValueError, match="predicts the unloaded step, not the compression step"):
        schema.check("compression", "ert.npz")
    other = FeatureSchema("unloaded", schema.features[:-1], 100)
    with pytest.raises(
        ValueError, match=r"xgb.json: the model was trained on the features .*retrain"
    ):
        other.check("unloaded", "xgb.json")
    with pytest.raises(ValueError, match=r"m\.ckpt: unreadable feature schema"):
        FeatureSchema.from_json('{"step": "unloaded"}', "m.ckpt")


def test_schema_refuses_inputs_of_an_older_definition(tmp_path):
    """A model trained before a feature was redefined (`REVISIONS`) is refused, however its
    names match: a file without revisions was trained on revision 1 of every input."""
    schema = FeatureSchema.of("compression", 70)
    assert dict(schema.revisions) == {f: 2 for f in REVISIONS}  # the plate edges, 2026-12-02
    assert FeatureSchema.from_json(schema.to_json()) == schema
    schema.check("compression")
    old = FeatureSchema("compression", schema.features, 70)  # as stored before 2026-12-05
    assert FeatureSchema.from_json(old.to_json()) == old
    with pytest.raises(ValueError, match=r"m\.ckpt: unreadable feature schema"):
        FeatureSchema.from_json(old.to_json()[:-1] + ', "revisions": [2]}', "m.ckpt")
    with pytest.raises(
        ValueError, match=r"xgb\.json: .*older definitions.*lower_plate_edge_y 1 -> 2.*retrain"
    ):
        old.check("compression", "xgb.json")
    booster = fit_xgboost(*data(), n_estimators=2, max_depth=2, n_jobs=1)
    with pytest.raises(ValueError, match="older definitions"):
        xgboost_schema(load_xgboost(save_xgboost(booster, tmp_path / "x.json", old))).check(
            "compression"
        )
    FeatureSchema.of("unloaded", 2).check("unloaded")  # no unloaded-state input was redefined
