"""The Att-BLSTM encoder-decoder of the reference paper (section 2.4.2), as plain nn.Modules.

Encoder: a bidirectional LSTM over a node's step sequence, pooled by the attention layer of
Zhou et al. (2016) with two cascaded activation stages: ``M = act1(H)``,
``alpha = softmax(w^T M)`` over the steps, ``h* = act2(H^T alpha)``. Decoder: an LSTM started
from ``h*`` that reads the encoder outputs step by step, with Luong et al. (2015) global
attention over them ("general" score), and a linear head to the node's x, y, z per step.

The classes here take every setting as an argument: the defaults of the network live in
`mammo_net.module.SurrogateModule` alone, the paper's activations per step in
`PAPER_ACTIVATIONS`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

ACTIVATIONS = {"tanh": torch.tanh, "relu": torch.relu, "sigmoid": torch.sigmoid}

#: The attention layer's two activation stages of the paper's model of each simulation step.
PAPER_ACTIVATIONS = {"unloaded": ("tanh", "relu"), "compression": ("sigmoid", "sigmoid")}


class AttentionPooling(nn.Module):
    """Zhou et al. (2016): ``h* = act2(H^T softmax(w^T act1(H)))``, (B, T, D) -> (B, D)."""

    def __init__(self, dim: int, first: str, second: str) -> None:
        super().__init__()
        for name in (first, second):
            if name not in ACTIVATIONS:
                raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {name!r}")
        self.first, self.second = ACTIVATIONS[first], ACTIVATIONS[second]
        self.w = nn.Linear(dim, 1, bias=False)

    def forward(self, H: torch.Tensor) -> torch.Tensor:
        alpha = torch.softmax(self.w(self.first(H)), dim=1)  # (B, T, 1)
        return self.second((H * alpha).sum(dim=1))  # (B, D)


class AttBLSTM(nn.Module):
    """Per-node sequence model: features (B, T, F) -> coordinates (B, T, 3).

    Parameters
    ----------
    n_features : int
        F (11 for the unloaded state, 22 for compression).
    hidden : int
        Hidden size of each LSTM direction; the decoder has ``2 * hidden``.
    layers : int
        Stacked encoder LSTM layers.
    activations : (str, str)
        The attention layer's two stages, names of `ACTIVATIONS` (the paper's per step:
        `PAPER_ACTIVATIONS`).
    dropout : float
        Between stacked encoder layers and before the head.
    """

    def __init__(
        self,
        n_features: int,
        hidden: int,
        layers: int,
        activations: Sequence[str],
        dropout: float,
    ) -> None:
        super().__init__()
        self.encoder = nn.LSTM(
            n_features,
            hidden,
            num_layers=layers,
            batch_first=True,
            bidirectional=True,
            dropout=dropout if layers > 1 else 0.0,
        )
        d = 2 * hidden
        first, second = activations
        self.pool = AttentionPooling(d, first, second)
        self.decoder = nn.LSTM(d, d, batch_first=True)
        self.score = nn.Linear(d, d, bias=False)  # Luong "general": s_ts = dec_t W H_s
        self.combine = nn.Linear(2 * d, d)
        self.head = nn.Sequential(nn.Dropout(dropout), nn.Linear(d, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        H, _ = self.encoder(x)  # (B, T, 2h)
        h = self.pool(H)  # (B, 2h)
        state = (h.unsqueeze(0), torch.zeros_like(h).unsqueeze(0))  # (1, B, 2h) each
        dec, _ = self.decoder(H, state)  # (B, T, 2h)
        weights = torch.softmax(dec @ self.score(H).transpose(1, 2), dim=-1)  # (B, T, T)
        context = weights @ H  # (B, T, 2h)
        return self.head(torch.tanh(self.combine(torch.cat([context, dec], dim=-1))))  # (B, T, 3)
