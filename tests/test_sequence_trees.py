"""Whole sequences through the trees by step intervals give the row-by-row predictions."""

import numpy as np
import pytest
from conftest import tiny_trajectory

from datamodules.features import compression_features, unloaded_features
from mammo_net import baselines
from mammo_net.sequence_trees import (
    _ordered_keys,
    from_forest,
    from_xgboost,
    predict_sequences,
    sequence_predictor,
)


def sequences(n: int, n_steps: int, groups: int, seed: int) -> np.ndarray:
    """(n, T, 12): 8 node features (one of them coarse, so values tie with split points), the
    step index, a rising and a falling step feature per group, a per-group constant."""
    rng = np.random.default_rng(seed)
    X = np.empty((n, n_steps, 12), np.float32)
    X[:, :, :8] = rng.standard_normal((n, 1, 8))
    X[:, :, 2] = np.round(X[:, :, 2], 1)
    g = rng.integers(0, groups, n)[:, None]
    t = np.arange(1, n_steps + 1, dtype=np.float32)[None]
    X[:, :, 8] = t
    X[:, :, 9] = 0.1 * t * (1 + g)
    X[:, :, 10] = -0.05 * t - g
    X[:, :, 11] = 0.5 * g
    return X


def targets(X: np.ndarray) -> np.ndarray:
    return np.stack(
        [X[..., 0] * X[..., 9], np.sin(X[..., 8]) + X[..., 1], X[..., 10] * X[..., 2]], -1
    )


@pytest.fixture(scope="module")
def training_rows():
    X = sequences(300, 20, 3, seed=0)
    return X.reshape(-1, 12), targets(X).reshape(-1, 3)


@pytest.mark.parametrize("compiled", [True, False])
def test_xgboost_sequences_equal_its_rows(training_rows, compiled):
    booster = baselines.fit_xgboost(*training_rows, n_estimators=20, max_depth=5, n_jobs=1)
    X = sequences(200, 20, 4, seed=1)
    rows = baselines.predict_xgboost(booster, X.reshape(-1, 12)).reshape((*X.shape[:2], 3))
    got = predict_sequences(from_xgboost(booster), X, compiled)
    np.testing.assert_allclose(got, rows, atol=1e-5)
    assert np.abs(rows).max() > 1  # not a trivial model


@pytest.mark.parametrize("compiled", [True, False])
def test_forest_sequences_equal_its_rows(training_rows, compiled):
    forest = baselines.fit_ert(*training_rows, n_estimators=8, min_samples_leaf=2, n_jobs=1)
    X = sequences(200, 20, 4, seed=2)
    rows = forest.predict(X.reshape(-1, 12)).reshape((*X.shape[:2], 3))
    got = predict_sequences(from_forest(forest), X, compiled)
    np.testing.assert_allclose(got, rows, atol=1e-6)
    # Node features at the float32 nearest to a split threshold of theirs (above or below
    # it): scikit-learn compares float32 <= float64, this module float32 < float32.
    rng = np.random.default_rng(4)
    for c in range(8):
        t = forest.threshold[(forest.left >= 0) & (forest.feature == c)]
        X[:, :, c] = rng.choice(t, size=(len(X), 1)).astype(np.float32)
    rows = forest.predict(X.reshape(-1, 12)).reshape((*X.shape[:2], 3))
    np.testing.assert_allclose(predict_sequences(from_forest(forest), X, compiled), rows, atol=1e-6)


def test_features_that_do_not_separate_go_row_by_row(training_rows):
    booster = baselines.fit_xgboost(*training_rows, n_estimators=5, max_depth=3, n_jobs=1)
    X = sequences(50, 20, 2, seed=3)
    X[:, :, 9] = np.sin(X[:, :, 8])  # a step feature that is not monotone
    assert predict_sequences(from_xgboost(booster), X) is None
    X[0, :, 0] += np.arange(20)  # a node feature that varies over the steps
    assert predict_sequences(from_xgboost(booster), X) is None
    predict = sequence_predictor(
        from_xgboost(booster), lambda r: baselines.predict_xgboost(booster, r)
    )
    rows = baselines.predict_xgboost(booster, X.reshape(-1, 12)).reshape(50, 20, 3)
    np.testing.assert_array_equal(predict(X), rows)


@pytest.mark.parametrize("step", ["unloaded", "compression"])
def test_the_paper_features_separate(step):
    """On a breast's features the fast path is taken and equals XGBoost's rows."""
    make = unloaded_features if step == "unloaded" else compression_features
    blocks = [make(tiny_trajectory(lat, patient=p)) for p in range(3) for lat in "LR"]
    X = np.concatenate([f.transpose(1, 0, 2) for f, _, _ in blocks])  # (N, T, F)
    Y = np.concatenate([t.transpose(1, 0, 2) for _, t, _ in blocks])
    X = X + np.float32(0.01) * np.random.default_rng(0).standard_normal((len(X), 1, 1)).astype(
        np.float32
    ) * (np.arange(X.shape[-1]) < 3)  # distinct node coordinates
    booster = baselines.fit_xgboost(
        X.reshape(-1, X.shape[-1]), Y.reshape(-1, 3), n_estimators=10, max_depth=3, n_jobs=1
    )
    features = make(tiny_trajectory("R"))[0].transpose(1, 0, 2)
    got = predict_sequences(from_xgboost(booster), features)
    assert got is not None
    rows = baselines.predict_xgboost(booster, features.reshape(-1, features.shape[-1]))
    np.testing.assert_allclose(got.reshape(-1, 3), rows, atol=1e-5)


def test_ordered_keys_keep_the_order_of_floats():
    v = np.array([-np.inf, -3.5, -1e-30, -0.0, 0.0, 1e-30, 2.0, np.inf], np.float32)
    keys = _ordered_keys(v)
    assert (np.diff(keys[[0, 1, 2, 4, 5, 6, 7]]) > 0).all()
    assert keys[3] == keys[4]  # -0.0 == 0.0
