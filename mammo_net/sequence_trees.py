"""Tree ensembles evaluated on whole step sequences at once: every node's trajectory goes
through each tree as a few step intervals instead of one row per step.

A node's features over the recorded steps are of two kinds: *node features* (coordinates,
tissue, flags: the same at every step) and *step features* (the step index, the plates'
positions: the same for every node of a breast and monotone in the step). A split on a node
feature sends the node's whole sequence one way; a split on a step feature with threshold
``theta`` cuts the steps where the feature is below ``theta``, a prefix or a suffix of them,
so each (node, tree) pair follows one path per piece of a piecewise-constant partition of the
steps. `predict_sequences` follows those paths and adds each leaf's value to its step
interval (difference arrays and a cumulative sum over the steps). For XGBoost's compression
model on a breast of 593 nodes and 70 steps that is 1.6 M visited tree nodes instead of the
row-by-row traversal's 41 510 rows x 240 trees x 7 levels = 70 M, with the same values (the
same float32 comparisons as XGBoost and scikit-learn; sums in float64). The paths are
followed by a compiled kernel (numba: depth first, blocks of nodes in parallel), tested
against a NumPy reference that follows all of them together, one tree level at a time.

`TreeEnsemble` holds the trees as flat arrays, read from an XGBoost booster's JSON or from a
`mammo_net.baselines.Forest`; `sequence_predictor` falls back to the model's own row
predictions when the features do not separate (a step feature that is not monotone).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
import xgboost as xgb
from numpy.typing import NDArray

from mammo_net.baselines import Forest


@dataclass(frozen=True)
class TreeEnsemble:
    """Regression trees as concatenated arrays; a row goes left where
    ``x[feature] < threshold`` (float32 comparison).

    Attributes
    ----------
    left, right : (M,) int32
        Children of each tree node; ``-1`` at leaves.
    feature : (M,) int32
        Split feature of inner nodes.
    threshold : (M,) float32
        Split threshold of inner nodes (strict ``<`` goes left).
    value : (M, 3) float64
        Leaf outputs per coordinate (zero at inner nodes).
    roots : (K,) int32
        First node of each tree.
    base : (3,) float64
        Added to the sum over trees.
    scale : float
        The sum over trees is multiplied by it (1 for boosting, 1 / K for a forest's mean).
    """

    left: NDArray[np.int32]
    right: NDArray[np.int32]
    feature: NDArray[np.int32]
    threshold: NDArray[np.float32]
    value: NDArray[np.float64]
    roots: NDArray[np.int32]
    base: NDArray[np.float64]
    scale: float

    @functools.cached_property
    def packed(self) -> NDArray[np.int32]:
        """(M, 4) int32 rows for the compiled kernel, one cache line per visited node: (left,
        right, feature, threshold bits) at inner nodes, (-1, value bits) at leaves (the
        values in float32)."""
        inner = self.left >= 0
        rows = np.stack([self.left, self.right, self.feature, self.threshold.view(np.int32)], 1)
        leaf_values = self.value[~inner].astype(np.float32).view(np.int32)  # (leaves, 3)
        rows[~inner, 1:] = leaf_values
        return np.ascontiguousarray(rows)

    @functools.cached_property
    def max_depth(self) -> int:
        """The number of splits on the longest root-to-leaf path."""
        depth, level = -1, self.roots
        while len(level):
            depth += 1
            inner = level[self.left[level] >= 0]
            level = np.concatenate([self.left[inner], self.right[inner]])
        return depth


def from_xgboost(booster: xgb.Booster) -> TreeEnsemble:
    """The trees of a squared-error booster with one tree per output (``one_output_per_tree``),
    from its JSON model: XGBoost sends ``x < split_condition`` left, and a leaf's
    ``split_condition`` is its (learning-rate scaled) value."""
    model = json.loads(booster.save_raw(raw_format="json"))["learner"]
    n_targets = int(model["learner_model_param"].get("num_target", 1))
    if n_targets != 3:
        raise ValueError(f"the booster predicts {n_targets} outputs, not x, y, z")
    base = np.atleast_1d(np.asarray(json.loads(model["learner_model_param"]["base_score"])))
    trees = model["gradient_booster"]["model"]
    parts, roots, offset = [], [], 0
    for tree, target in zip(trees["trees"], trees["tree_info"], strict=True):
        left, right = np.asarray(tree["left_children"]), np.asarray(tree["right_children"])
        inner = left >= 0
        condition = np.asarray(tree["split_conditions"], np.float32)
        value = np.zeros((len(left), 3))
        value[:, target] = np.where(inner, 0.0, condition)
        feature = np.where(inner, tree["split_indices"], 0)
        parts.append((np.where(inner, left + offset, -1), np.where(inner, right + offset, -1),
                      feature, condition, value))  # fmt: skip
        roots.append(offset)
        offset += len(left)
    left, right, feature, threshold, value = (np.concatenate(a) for a in zip(*parts, strict=True))
    return TreeEnsemble(
        left.astype(np.int32),
        right.astype(np.int32),
        feature.astype(np.int32),
        threshold,
        value,
        np.array(roots, np.int32),
        np.broadcast_to(base, 3).astype(np.float64),
        1.0,
    )


def from_forest(forest: Forest) -> TreeEnsemble:
    """The trees of a `Forest`. scikit-learn sends ``x <= threshold`` left, with ``x`` in
    float32 and a float64 threshold; for float32 ``x`` that is ``x < t`` with ``t`` the
    smallest float32 above the largest float32 not above the threshold."""
    t64 = np.asarray(forest.threshold, np.float64)
    t32 = t64.astype(np.float32)
    t32 = np.where(t32 > t64, np.nextafter(t32, np.float32(-np.inf)), t32)
    inner = forest.left >= 0
    return TreeEnsemble(
        forest.left.astype(np.int32),
        forest.right.astype(np.int32),
        np.where(inner, forest.feature, 0).astype(np.int32),
        np.nextafter(t32, np.float32(np.inf)),
        np.where(inner[:, None], 0.0, np.asarray(forest.value, np.float64)),
        forest.roots.astype(np.int32),
        np.zeros(3),
        1.0 / len(forest.roots),
    )


def _ordered_keys(values: NDArray[np.float32]) -> NDArray[np.int64]:
    """An order-preserving map of float32 values to non-negative integers below 2^32."""
    positive_zero = np.asarray(values, np.float32) + np.float32(0)  # -0.0 -> +0.0
    bits = np.ascontiguousarray(positive_zero).view(np.uint32).astype(np.int64)
    return np.where(bits >= 2**31, 2**32 - 1 - bits, bits + 2**31)


@dataclass(frozen=True)
class _StepFeatures:
    """The step features of every sequence group, sorted for counting steps below a value.

    ``keys`` holds, per (group, step feature) block ``b``, the block's T values as
    ``b * 2^32 + ordered key``, ascending; ``rising[b]`` says whether the values rise with the
    step (or are constant) rather than fall."""

    group: NDArray[np.intp]  # (S,) group of each sequence
    column: NDArray[np.intp]  # (F,) index among the step features, -1 for node features
    sorted: NDArray[np.float32]  # (G, Fs, T): each block's values, ascending
    keys: NDArray[np.int64]  # (G * Fs * T,)
    rising: NDArray[np.bool_]  # (G * Fs,)
    n_step_features: int


def _step_features(X: NDArray[np.float32]) -> tuple[NDArray[np.bool_], _StepFeatures] | None:
    """Split the features of ``X`` (S, T, F) into node and step features, and the sequences
    into groups of equal step features (a breast at one thickness); None if they do not
    separate (a feature varying over both nodes and steps, or a non-monotone step feature)."""
    S, T, F = X.shape
    is_node = (X == X[:, :1]).all(axis=(0, 1))  # (F,)
    steps = np.flatnonzero(~is_node)
    V = X[:, :, steps]  # (S, T, Fs)
    if not len(steps) or (V == V[:1]).all():
        group, unique = np.zeros(S, np.intp), V[:1]
    else:  # sequences with equal step features (one breast at one thickness), by a hash
        bits = (V.reshape(S, -1) + np.float32(0)).view(np.uint32).astype(np.uint64)
        weights = np.random.default_rng(0).integers(1, 2**63, bits.shape[1], dtype=np.uint64)
        _, first, group = np.unique(
            (bits * (weights | np.uint64(1))).sum(axis=1), return_index=True, return_inverse=True
        )
        unique, group = V[first], group.reshape(-1)
        if not (V == unique[group]).all():  # a hash collision (never seen): row by row
            return None
    d = np.diff(unique, axis=1)  # (G, T-1, Fs)
    rising, falling = (d >= 0).all(axis=1), (d <= 0).all(axis=1)  # (G, Fs)
    if not (rising | falling).all():
        return None
    ordered = np.sort(unique.transpose(0, 2, 1), axis=-1)  # (G, Fs, T)
    blocks = ordered.reshape(-1, T)
    keys = _ordered_keys(blocks) + (np.arange(len(blocks), dtype=np.int64) << 32)[:, None]
    column = np.full(F, -1, np.intp)
    column[steps] = np.arange(len(steps))
    return is_node, _StepFeatures(group, column, ordered, keys.ravel(), rising.ravel(), len(steps))


def predict_sequences(
    ens: TreeEnsemble, X: NDArray, compiled: bool = True
) -> NDArray[np.float64] | None:
    """The ensemble's predictions for every step of every sequence, by step intervals.

    Parameters
    ----------
    ens : TreeEnsemble
    X : (S, T, F)
        Features per sequence (node) and step, compared in float32.
    compiled : bool
        Follow the paths with the compiled kernel (`_paths_compiled`) or with the NumPy
        reference (`_paths_numpy`: the same values, several times slower).

    Returns
    -------
    (S, T, 3) float64, or None when the features do not separate into node and step
    features (then predict row by row).
    """
    X = np.asarray(X, np.float32)
    split = _step_features(X)
    if split is None:
        return None
    is_node, sf = split
    node_values = np.ascontiguousarray(X[:, 0])  # (S, F): the node features
    if compiled:
        packed = ens.packed
        diff = _paths_compiled(
            packed, packed.view(np.float32), ens.roots,
            node_values, is_node, sf.column, sf.group, sf.sorted,
            sf.rising.reshape(sf.sorted.shape[:2]), ens.max_depth,
            min(len(node_values), numba.get_num_threads()),
        )  # fmt: skip
    else:
        diff = _paths_numpy(ens, node_values, is_node, sf, X.shape[1])
    return np.cumsum(diff, axis=1)[:, :-1] * ens.scale + ens.base


def _paths_numpy(
    ens: TreeEnsemble, node_values: NDArray, is_node: NDArray, sf: _StepFeatures, T: int
) -> NDArray[np.float64]:
    """Difference arrays (S, T + 1, 3) of the leaf values over the step intervals, following
    all (sequence, tree) paths together, one tree level per iteration."""
    S = len(node_values)
    K = len(ens.roots)
    seq = np.repeat(np.arange(S, dtype=np.int32), K)
    node = np.tile(ens.roots, S)
    lo = np.zeros(len(seq), np.int32)
    hi = np.full(len(seq), T, np.int32)
    finished = []  # (sequence, leaf, lo, hi) of the paths that reached a leaf
    while len(seq):
        leaf = ens.left[node] < 0
        if leaf.any():
            finished.append((seq[leaf], node[leaf], lo[leaf], hi[leaf]))
            inner = ~leaf
            seq, node, lo, hi = seq[inner], node[inner], lo[inner], hi[inner]
        f = ens.feature[node]
        theta = ens.threshold[node]
        on_node = is_node[f]
        # Node features: the whole interval goes one way.
        a = on_node
        go_left = node_values[seq[a], f[a]] < theta[a]
        n_seq, n_node = [seq[a]], [np.where(go_left, ens.left[node[a]], ens.right[node[a]])]
        n_lo, n_hi = [lo[a]], [hi[a]]
        # Step features: c steps lie below theta; the left set is a prefix (rising values) or
        # a suffix (falling values) of the steps, the right set its complement.
        b = ~on_node
        if b.any():
            s_b, j_b, lo_b, hi_b = seq[b], node[b], lo[b], hi[b]
            block = sf.group[s_b] * sf.n_step_features + sf.column[f[b]]
            query = (block.astype(np.int64) << 32) + _ordered_keys(theta[b])
            c = (np.searchsorted(sf.keys, query) - block * T).astype(np.int32)
            rising = sf.rising[block]
            left_lo, left_hi = np.where(rising, 0, T - c), np.where(rising, c, T)
            right_lo, right_hi = np.where(rising, c, 0), np.where(rising, T, T - c)
            for child, clo, chi in ((ens.left, left_lo, left_hi), (ens.right, right_lo, right_hi)):
                new_lo, new_hi = np.maximum(lo_b, clo), np.minimum(hi_b, chi)
                keep = new_lo < new_hi
                n_seq.append(s_b[keep])
                n_node.append(child[j_b[keep]])
                n_lo.append(new_lo[keep])
                n_hi.append(new_hi[keep])
        seq, node, lo, hi = (np.concatenate(p) for p in (n_seq, n_node, n_lo, n_hi))
    s, j, lo, hi = (np.concatenate(p) for p in zip(*finished, strict=True))
    diff = np.empty((S, T + 1, 3))
    for k in range(3):
        w = ens.value[j, k]
        diff[:, :, k] = (
            np.bincount(s * (T + 1) + lo, w, S * (T + 1))
            - np.bincount(s * (T + 1) + hi, w, S * (T + 1))
        ).reshape(S, T + 1)
    return diff


@numba.njit(cache=True)
def _walk(s, root, lo, hi, nodes, floats, node_values, is_node, column, g, ordered, rising,
          stack, diff):  # fmt: skip
    """Add the leaf values of sequence ``s``'s paths through one tree to ``diff[s]``."""
    T = ordered.shape[2]
    stack[0, 0], stack[0, 1], stack[0, 2] = root, lo, hi
    top = 1
    while top > 0:
        top -= 1
        j, lo, hi = stack[top, 0], stack[top, 1], stack[top, 2]
        while nodes[j, 0] >= 0:
            f, theta = nodes[j, 2], floats[j, 3]
            if is_node[f]:
                j = nodes[j, 0] if node_values[s, f] < theta else nodes[j, 1]
                continue
            values = ordered[g, column[f]]
            a, b = 0, T  # a = the number of steps with a value below theta
            while a < b:
                m = (a + b) // 2
                if values[m] < theta:
                    a = m + 1
                else:
                    b = m
            if rising[g, column[f]]:  # left: the first a steps; right: the others
                left_lo, left_hi, right_lo, right_hi = 0, a, a, T
            else:  # left: the last a steps
                left_lo, left_hi, right_lo, right_hi = T - a, T, 0, T - a
            l_lo, l_hi = max(lo, left_lo), min(hi, left_hi)
            r_lo, r_hi = max(lo, right_lo), min(hi, right_hi)
            if l_lo < l_hi and r_lo < r_hi:  # both sides: the right one waits on the stack
                stack[top, 0], stack[top, 1], stack[top, 2] = nodes[j, 1], r_lo, r_hi
                top += 1
                j, lo, hi = nodes[j, 0], l_lo, l_hi
            elif l_lo < l_hi:
                j, lo, hi = nodes[j, 0], l_lo, l_hi
            else:
                j, lo, hi = nodes[j, 1], r_lo, r_hi
        for k in range(3):  # the leaf's values
            diff[s, lo, k] += floats[j, 1 + k]
            diff[s, hi, k] -= floats[j, 1 + k]


@numba.njit(parallel=True, cache=True)
def _paths_compiled(nodes, floats, roots, node_values, is_node, column, group, ordered,
                    rising, max_depth, n_blocks):  # fmt: skip
    """`_paths_numpy` depth first: each sequence's paths through each tree on a stack of
    (tree node, lo, hi), with one pending sibling per tree level at most. ``n_blocks``
    contiguous blocks of sequences run in parallel, with the trees in the outer loop (a tree's
    upper levels stay in cache over a block). A split on a step feature counts the steps
    below its threshold by bisection in the sorted values ``ordered`` (G, Fs, T)."""
    S = node_values.shape[0]
    T = ordered.shape[2]
    diff = np.zeros((S, T + 1, 3))
    for block in numba.prange(n_blocks):
        stack = np.empty((max_depth + 2, 3), np.int64)  # one pending sibling per level
        for root in roots:
            for s in range(block * S // n_blocks, (block + 1) * S // n_blocks):
                _walk(s, root, 0, T, nodes, floats, node_values, is_node, column, group[s],
                      ordered, rising, stack, diff)  # fmt: skip
    return diff


def sequence_predictor(
    ens: TreeEnsemble | None, predict_rows: Callable[[NDArray], NDArray]
) -> Callable[[NDArray], NDArray[np.float32]]:
    """``(N, T, F) -> (N, T, 3)`` float32 by `predict_sequences`, or row by row with
    ``predict_rows`` ``(rows, F) -> (rows, 3)`` where the features do not separate (always,
    without ``ens``)."""

    def predict(features: NDArray) -> NDArray[np.float32]:
        out = None if ens is None else predict_sequences(ens, features)
        if out is None:
            f = np.asarray(features, np.float32)
            out = np.asarray(predict_rows(f.reshape(-1, f.shape[-1]))).reshape(*f.shape[:2], 3)
        return out.astype(np.float32)

    return predict
