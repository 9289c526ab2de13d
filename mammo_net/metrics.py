"""Errors of predicted node trajectories against the FE ground truth (reference paper, 2.5).

Equation 2: the RMSE of a node is ``sqrt((e_x^2 + e_y^2 + e_z^2) / 3)``, mm. A breast's error
is the mean over its nodes (and, for "all steps", over its recorded steps); a model's error is
the mean / median / standard deviation over the breasts.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray

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


class BreastErrors:
    """Accumulates node RMSEs per breast over batches of node sequences (any order).

    ``update`` takes predictions and targets in normalised units with each node's breast index
    and normalisation scale (mm per unit), so the errors come out in millimetres.
    """

    def __init__(self) -> None:
        self.sums: dict[int, NDArray] = {}  # breast -> [sum all-steps RMSE, sum last-step, nodes]

    def update(
        self,
        prediction: torch.Tensor,
        target: torch.Tensor,
        breast: torch.Tensor,
        scale: torch.Tensor,
    ) -> None:
        """``prediction``, ``target``: (B, T, 3); ``breast``, ``scale``: (B,)."""
        e = node_rmse(prediction.detach(), target) * scale[:, None]  # (B, T), mm
        rows = torch.stack([e.mean(1), e[:, -1], torch.ones_like(scale)], 1).double().cpu().numpy()
        ids = breast.cpu().numpy()
        for b in np.unique(ids):
            self.sums[int(b)] = self.sums.get(int(b), 0.0) + rows[ids == b].sum(0)

    def compute(self) -> dict[str, float]:
        """``{all_steps,last_step}_{mean,median,std}`` over the breasts seen, mm."""
        if not self.sums:
            return {}
        per = np.array([s[:2] / s[2] for s in self.sums.values()])
        out = {}
        for j, name in enumerate(("all_steps", "last_step")):
            out.update({f"{name}_{k}": v for k, v in summarize(per[:, j]).items()})
        return out

    def reset(self) -> None:
        self.sums = {}
