"""Errors of predicted node trajectories against the FE ground truth (reference paper, 2.5).

Equation 2: the RMSE of a node is ``sqrt((e_x^2 + e_y^2 + e_z^2) / 3)``, mm. A breast's error
is the mean over its nodes (and, for "all steps", over its recorded steps); a model's error is
the mean / median / standard deviation over the breasts.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

Array = NDArray | torch.Tensor


def node_rmse(prediction: Array, target: Array) -> Array:
    """Equation 2 per node (and step): ``sqrt(mean_k (p_k - t_k)^2)`` over the last axis (3)."""
    return (((prediction - target) ** 2).mean(-1)) ** 0.5


def breast_rmse(prediction: NDArray, target: NDArray) -> dict[str, float]:
    """A breast's mean node RMSE over all steps and at the last step, mm.

    Parameters
    ----------
    prediction, target : (N, T, 3)
        Node coordinates per recorded step, mm.
    """
    e = node_rmse(np.asarray(prediction, float), np.asarray(target, float))  # (N, T)
    return {"all_steps": float(e.mean()), "last_step": float(e[:, -1].mean())}


def summarize(per_breast: Sequence[float]) -> dict[str, float]:
    """Mean, median and (population) standard deviation over breasts."""
    v = np.asarray(per_breast, float)
    return {"mean": float(v.mean()), "median": float(np.median(v)), "std": float(v.std())}


def summarize_breasts(per_breast: Sequence[dict[str, float]]) -> dict[str, float]:
    """``{all_steps,last_step}_{mean,median,std}`` over breasts from their `breast_rmse`."""
    out = {}
    for key in ("all_steps", "last_step"):
        out.update({f"{key}_{k}": v for k, v in summarize([p[key] for p in per_breast]).items()})
    return out


def comparison(metrics: dict[str, float], stage: str, network: str = "att_blstm") -> str:
    """Markdown table of the paper's Tables 3/4: (mean, median) +- std of the per-breast RMSE,
    mm, per model, from logged metrics ``{stage}/rmse_{all_steps,last_step}_{mean,median,std}_mm``
    (the network, named ``network``) and ``.../<model>`` (a baseline); fit times from
    ``<model>/fit_seconds``."""
    rows: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        match = re.fullmatch(rf"{stage}/rmse_(\w+)_mm(?:/(\w+))?", key)
        if match:
            rows.setdefault(match[2] or network, {})[match[1]] = value
    lines = [
        f"| model ({stage}) | all steps: (mean, median) +- std | last step: (mean, median) +- std |",
        "| --- | --- | --- |",
    ]
    for model, m in rows.items():
        cells = [
            f"({m[f'{c}_mean']:.2f}, {m[f'{c}_median']:.2f}) +- {m[f'{c}_std']:.2f}"
            if f"{c}_mean" in m
            else "-"
            for c in ("all_steps", "last_step")
        ]
        lines.append(f"| {model} | {cells[0]} | {cells[1]} |")
    times = [
        f"{k.split('/')[0]} {v:.0f} s" for k, v in metrics.items() if k.endswith("/fit_seconds")
    ]
    return "\n".join(lines) + "\n\nfit time: " + ", ".join(times) + "\n"


class BreastErrors(Metric):
    """Per-breast mean node RMSE accumulated over batches of node sequences (any order, any
    number of processes).

    ``update`` takes predictions and targets in normalised units with each node's breast index,
    normalisation scale (mm per unit) and dataset index, so the errors come out in millimetres.
    The node rows are concatenated across processes (DDP) and de-duplicated by dataset index
    (a distributed sampler pads its shards with repeated nodes), so every process computes the
    errors of the whole evaluated set, as one process would.
    """

    full_state_update = False

    def __init__(self) -> None:
        super().__init__()
        for name in ("node", "breast", "all_steps", "last_step"):
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(
        self,
        prediction: torch.Tensor,
        target: torch.Tensor,
        breast: torch.Tensor,
        scale: torch.Tensor,
        node: torch.Tensor,
    ) -> None:
        """``prediction``, ``target``: (B, T, 3); ``breast``, ``scale``, ``node``: (B,)."""
        e = node_rmse(prediction.detach(), target).double() * scale[:, None]  # (B, T), mm
        self.node.append(node.long())
        self.breast.append(breast.long())
        self.all_steps.append(e.mean(1))
        self.last_step.append(e[:, -1])

    def compute(self) -> dict[str, float]:
        """``{all_steps,last_step}_{mean,median,std}`` over the breasts seen, mm."""
        if isinstance(self.node, list) and not self.node:  # a tensor once synced across ranks
            return {}
        node, breast, all_steps, last_step = (
            dim_zero_cat(getattr(self, n)).cpu().numpy()
            for n in ("node", "breast", "all_steps", "last_step")
        )
        _, first = np.unique(node, return_index=True)
        ids, breast = np.unique(breast[first], return_inverse=True)
        counts = np.bincount(breast, minlength=len(ids))
        per = {  # per-breast mean node RMSE, (breasts,) each
            name: np.bincount(breast, weights=e[first], minlength=len(ids)) / counts
            for name, e in (("all_steps", all_steps), ("last_step", last_step))
        }
        return summarize_breasts(
            [dict(zip(per, values, strict=True)) for values in zip(*per.values(), strict=True)]
        )
