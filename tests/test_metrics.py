"""Errors in millimetres: equation 2, per-breast means, and the DDP-safe accumulator."""

import numpy as np
import torch

from mammo_net.metrics import BreastErrors, breast_rmse, node_rmse, summarize


def test_node_rmse_is_equation_2():
    e = node_rmse(np.array([[3.0, 0.0, 4.0]]), np.zeros((1, 3)))
    np.testing.assert_allclose(e, [np.sqrt(25 / 3)])


def test_breast_errors_match_per_breast_rmse_with_repeats_in_any_order():
    rng = np.random.default_rng(0)
    sizes, T = (5, 3, 4), 6
    scales = rng.uniform(10, 50, len(sizes))
    pred = [rng.normal(size=(n, T, 3)) for n in sizes]
    true = [rng.normal(size=(n, T, 3)) for n in sizes]
    per = [breast_rmse(p * s, t * s) for p, t, s in zip(pred, true, scales, strict=True)]
    expected = {}
    for key in ("all_steps", "last_step"):
        expected.update({f"{key}_{k}": v for k, v in summarize([p[key] for p in per]).items()})

    rows = [(b, i) for b, n in enumerate(sizes) for i in range(n)]
    node = np.arange(len(rows))
    order = np.concatenate([rng.permutation(len(rows)), [0, 4, 4]])  # padded like DDP shards
    metric = BreastErrors()
    for chunk in np.array_split(order, 4):
        b = torch.tensor([rows[k][0] for k in chunk])
        metric.update(
            torch.tensor(np.stack([pred[rows[k][0]][rows[k][1]] for k in chunk])),
            torch.tensor(np.stack([true[rows[k][0]][rows[k][1]] for k in chunk])),
            b,
            torch.tensor(scales[b.numpy()]),
            torch.tensor(node[chunk]),
        )
    got = metric.compute()
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_allclose(got[key], value, rtol=1e-12)
    metric.reset()
    assert metric.compute() == {}
