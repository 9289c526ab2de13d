"""The tree baselines of the reference paper: extremely randomized trees and XGBoost.

Pure functions fit a model on flat ``(node, step)`` rows and predict coordinates; the models
are saved without pickle: XGBoost as its own JSON, the extra trees as arrays in an ``.npz``
(`save_forest`/`load_forest`, a `Forest` predicts exactly as scikit-learn does). The thin
Lightning callbacks in `mammo_net.callbacks` fit them on the DataModule's training split and
log their errors under the network's metric names.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np
import xgboost as xgb
from numpy.typing import NDArray
from sklearn.ensemble import ExtraTreesRegressor
from sklearn.tree._tree import NODE_DTYPE, Tree

from datamodules.features import FeatureSchema
from fem.contract.atomic import atomic_path
from fem.contract.trajectory import read_npz, reading_file

#: The arrays of a `Forest` file.
FOREST_FIELDS = ("left", "right", "feature", "threshold", "value", "roots")


def stack_rows(rows: Iterable[tuple[NDArray, NDArray]]) -> tuple[NDArray, NDArray]:
    """One (rows, F) feature matrix and (rows, 3) target matrix from per-breast row blocks,
    filled into preallocated arrays (the blocks are read once; no second full copy)."""
    blocks = list(rows)
    n = sum(len(f) for f, _ in blocks)
    X = np.empty((n, blocks[0][0].shape[1]), np.float32)
    Y = np.empty((n, 3), np.float32)
    i = 0
    for f, t in blocks:
        X[i : i + len(f)], Y[i : i + len(f)] = f, t
        i += len(f)
    return X, Y


def fit_xgboost(
    X: NDArray,
    Y: NDArray,
    n_estimators: int = 80,
    learning_rate: float = 0.08,
    min_child_weight: float = 6,
    max_depth: int = 7,
    n_jobs: int = 0,
    seed: int = 0,
) -> xgb.Booster:
    """Gradient-boosted trees (squared error, one multi-output model) on rows ``X`` -> ``Y``."""
    data = xgb.QuantileDMatrix(X, Y)
    params = {
        "objective": "reg:squarederror",
        "learning_rate": learning_rate,
        "min_child_weight": min_child_weight,
        "max_depth": max_depth,
        "tree_method": "hist",
        "multi_strategy": "one_output_per_tree",
        "nthread": n_jobs,
        "seed": seed,
    }
    return xgb.train(params, data, num_boost_round=n_estimators)


def predict_xgboost(model: xgb.Booster, X: NDArray) -> NDArray[np.float32]:
    """(rows, 3) predictions."""
    return model.inplace_predict(X).reshape(len(X), 3).astype(np.float32)


@dataclass
class Forest:
    """An extremely randomized forest as plain arrays (all trees concatenated).

    ``left``, ``right``, ``feature`` (int), ``threshold`` (float) per node, ``value`` (nodes, 3)
    the leaf means, ``roots`` the first node of each tree; leaves have ``left == -1``.
    """

    left: NDArray
    right: NDArray
    feature: NDArray
    threshold: NDArray
    value: NDArray
    roots: NDArray

    def predict(self, X: NDArray) -> NDArray[np.float32]:
        """(rows, 3): the mean of the trees' leaf values, as scikit-learn computes it."""
        X = np.asarray(X, np.float32)
        total = np.zeros((len(X), 3))
        rows = np.arange(len(X))
        for root in self.roots:
            node = np.full(len(X), root)
            inner = self.left[node] >= 0
            while inner.any():
                n = node[inner]
                go_left = X[rows[inner], self.feature[n]] <= self.threshold[n]
                node[inner] = np.where(go_left, self.left[n], self.right[n])
                inner = self.left[node] >= 0
            total += self.value[node]
        return (total / len(self.roots)).astype(np.float32)

    def validate(self, source: str = "forest", n_features: int | None = None) -> None:
        """Raise ``ValueError`` naming ``source`` unless the arrays are a forest that
        `predict` and `compiled` can traverse: integer links, every tree's nodes contiguous
        from its root, children after their parent within the tree (no cycle), features
        below ``n_features`` (when known), finite thresholds and values."""
        problem = _forest_problem(self, n_features)
        if problem:
            raise ValueError(f"{source}: not a valid ERT forest: {problem}")

    def compiled(
        self, n_features: int, threads: int = 2
    ) -> Callable[[NDArray], NDArray[np.float32]]:
        """The same predictions by scikit-learn's compiled tree traversal: each tree rebuilt as
        a ``sklearn.tree._tree.Tree`` from the arrays (nothing unpickled), the trees shared
        among ``threads`` threads (the traversal releases the GIL); 5-10x faster than
        `predict`, which stays the reference it is tested against."""
        bounds = [*self.roots.tolist(), len(self.left)]
        trees = []
        for a, b in pairwise(bounds):
            inner = self.left[a:b] >= 0
            nodes = np.zeros(b - a, dtype=NODE_DTYPE)
            nodes["left_child"] = np.where(inner, self.left[a:b] - a, -1)
            nodes["right_child"] = np.where(inner, self.right[a:b] - a, -1)
            nodes["feature"] = np.where(inner, self.feature[a:b], -2)
            nodes["threshold"] = np.where(inner, self.threshold[a:b], -2.0)
            tree = Tree(n_features, np.ones(3, dtype=np.intp), 3)
            values = np.ascontiguousarray(self.value[a:b, :, None], dtype=np.float64)
            tree.__setstate__(
                {"max_depth": b - a, "node_count": b - a, "nodes": nodes, "values": values}
            )
            trees.append(tree)

        def predict(X: NDArray) -> NDArray[np.float32]:
            X = np.ascontiguousarray(X, dtype=np.float32)
            parts = [trees[i::threads] for i in range(threads)]
            with ThreadPoolExecutor(threads) as pool:
                sums = pool.map(lambda ts: sum(t.predict(X)[:, :, 0] for t in ts), parts)
                return (sum(sums) / len(trees)).astype(np.float32)

        return predict


def _forest_problem(forest: Forest, n_features: int | None) -> str | None:
    """What is wrong with ``forest``'s arrays (`Forest.validate`), or None."""
    for name in FOREST_FIELDS:
        kinds = "iuf" if name in ("threshold", "value") else "iu"
        if getattr(forest, name).dtype.kind not in kinds:
            return f"field '{name}' holds {getattr(forest, name).dtype} values"
    left, right, feature, roots = forest.left, forest.right, forest.feature, forest.roots
    if left.ndim != 1 or roots.ndim != 1 or not left.size or not roots.size:
        return "fields 'left' and 'roots' must be non-empty 1-D arrays"
    n = len(left)
    shapes = {"right": (n,), "feature": (n,), "threshold": (n,), "value": (n, 3)}
    for name, shape in shapes.items():
        if getattr(forest, name).shape != shape:
            return f"field '{name}' has shape {getattr(forest, name).shape}, expected {shape}"
    if roots[0] != 0 or (np.diff(roots) <= 0).any() or roots[-1] >= n:
        return "field 'roots' must start at 0 and increase within the nodes"
    inner = left >= 0
    node = np.flatnonzero(inner)
    end = np.append(roots[1:], n)[np.searchsorted(roots, node, side="right") - 1]
    leaf_ok = (left[~inner] == -1) & (right[~inner] == -1)
    links_ok = [(node < c) & (c < end) for c in (left[inner], right[inner])]
    if not leaf_ok.all() or not all(ok.all() for ok in links_ok):
        return "children must follow their parent within its tree (leaves: -1)"
    if (feature[inner] < 0).any():
        return "a split feature is negative"
    if n_features is not None and (feature[inner] >= n_features).any():
        return f"a split feature is not below the schema's {n_features} features"
    if not (np.isfinite(forest.threshold).all() and np.isfinite(forest.value).all()):
        return "thresholds and values must be finite"
    return None


def fit_ert(
    X: NDArray,
    Y: NDArray,
    n_estimators: int = 100,
    min_samples_leaf: int = 1,
    max_depth: int | None = None,
    max_samples: int | None = None,
    n_jobs: int = -1,
    seed: int = 0,
) -> Forest:
    """Extremely randomized trees (scikit-learn) on rows ``X`` -> ``Y``, as a `Forest`.

    ``max_samples`` rows drawn per tree (with replacement) keep a forest on tens of millions
    of rows tractable; ``None`` grows every tree on all rows, as the paper's ERT.
    """
    model = ExtraTreesRegressor(
        n_estimators=n_estimators,
        min_samples_leaf=min_samples_leaf,
        max_depth=max_depth,
        bootstrap=max_samples is not None,
        max_samples=None if max_samples is None else min(max_samples, len(X)),
        n_jobs=n_jobs,
        random_state=seed,
    ).fit(X, Y)
    return forest_arrays(model)


def forest_arrays(model: ExtraTreesRegressor) -> Forest:
    """The fitted scikit-learn forest's trees as concatenated arrays."""
    parts, offset, roots = [], 0, []
    for est in model.estimators_:
        t = est.tree_
        shift = np.where(t.children_left >= 0, offset, 0)
        parts.append(
            (
                t.children_left + shift,
                t.children_right + shift,
                t.feature,
                t.threshold,
                t.value[:, :, 0],
            )
        )
        roots.append(offset)
        offset += t.node_count
    left, right, feature, threshold, value = (np.concatenate(a) for a in zip(*parts, strict=True))
    return Forest(left, right, feature, threshold, value, np.array(roots))


def save_forest(forest: Forest, path: str | Path, schema: FeatureSchema | None = None) -> Path:
    """Write a `Forest` (and the feature ``schema`` it was trained on) as a plain ``.npz``
    (no pickle), atomically."""
    path = Path(path)
    arrays = {k: v for k, v in vars(forest).items() if isinstance(v, np.ndarray)}
    if schema is not None:
        arrays["feature_schema"] = np.array(schema.to_json())
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


def load_forest(path: str | Path) -> Forest:
    """Read a `Forest` written by `save_forest` (never unpickles), checked
    (`Forest.validate`, split features within the stored schema's).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        An empty, truncated or corrupt file, another kind of file, an ``.npz`` without the
        forest's arrays, or arrays that are not a valid forest.
    """
    arrays = read_npz(path, "an ERT model (.npz)")
    missing = [k for k in FOREST_FIELDS if k not in arrays]
    if missing:
        raise ValueError(
            f"{path}: not an ERT model file: field(s) {', '.join(map(repr, missing))} missing "
            f"(fields: {', '.join(sorted(arrays)) or 'none'})"
        )
    forest = Forest(**{k: arrays[k] for k in FOREST_FIELDS})
    schema = _stored_schema(arrays, path)
    forest.validate(str(path), None if schema is None else len(schema.features))
    return forest


def _stored_schema(arrays: dict[str, NDArray], path: str | Path) -> FeatureSchema | None:
    text = arrays.get("feature_schema")
    return None if text is None else FeatureSchema.from_json(str(text), str(path))


def forest_schema(path: str | Path) -> FeatureSchema | None:
    """The feature schema stored by `save_forest`, if any (errors as `load_forest`)."""
    return _stored_schema(read_npz(path, "an ERT model (.npz)"), path)


def save_xgboost(model: xgb.Booster, path: str | Path, schema: FeatureSchema | None = None) -> Path:
    """XGBoost's own JSON (``.json``) or UBJSON (``.ubj``) format, with the feature ``schema``
    as the booster attribute ``feature_schema``, atomically."""
    path = Path(path)
    if schema is not None:
        model = model.copy()  # leave the caller's booster as it is
        model.set_attr(feature_schema=schema.to_json())
    with atomic_path(path) as tmp:
        model.save_model(str(tmp))  # the format follows the suffix: .json or .ubj
    return path


def load_xgboost(path: str | Path) -> xgb.Booster:
    """Read a model written by `save_xgboost` (XGBoost's JSON or UBJSON, by suffix; never
    unpickles), checked to be a tree booster with the three outputs x, y, z.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        An empty, truncated or corrupt file, another kind of file, or another model (a
        linear booster, another number of outputs).
    """
    model = xgb.Booster()
    with reading_file(path, "an XGBoost model (.json/.ubj)", b"{") as p:
        model.load_model(str(p))
        learner = json.loads(model.save_config())["learner"]
        booster = learner["gradient_booster"]["name"]
        n_targets = int(learner["learner_model_param"].get("num_target", 1))
    if booster != "gbtree" or n_targets != 3:
        raise ValueError(
            f"{path}: another model: an XGBoost {booster} booster with {n_targets} output(s), "
            "not a tree model of the three coordinates x, y, z as train.py writes"
        )
    return model


def xgboost_schema(model: xgb.Booster, source: str = "model") -> FeatureSchema | None:
    """The feature schema stored by `save_xgboost`, if any."""
    text = model.attr("feature_schema")
    return FeatureSchema.from_json(text, source) if text else None
