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


def mlp(n_in: int, hidden: int, n_out: int, norm: bool = True) -> nn.Sequential:
    """Two linear layers with a SiLU between them, and a LayerNorm on the output (MeshGraphNets)."""
    layers = [nn.Linear(n_in, hidden), nn.SiLU(), nn.Linear(hidden, n_out)]
    return nn.Sequential(*layers, nn.LayerNorm(n_out)) if norm else nn.Sequential(*layers)


class MessagePassing(nn.Module):
    """One MeshGraphNets processor block, residual: edges from their two nodes, nodes from
    the mean of their incoming edges (a mean, so a finer mesh's larger stencil does not scale
    the update). The edge MLP's first layer is split per input, so the node terms are computed
    once per node, not once per edge."""

    def __init__(self, hidden: int) -> None:
        super().__init__()
        self.edge_self = nn.Linear(hidden, hidden)
        self.edge_source = nn.Linear(hidden, hidden, bias=False)
        self.edge_target = nn.Linear(hidden, hidden, bias=False)
        self.edge_out = nn.Sequential(nn.SiLU(), nn.Linear(hidden, hidden), nn.LayerNorm(hidden))
        self.node = mlp(2 * hidden, hidden, hidden)

    def forward(
        self, h: torch.Tensor, e: torch.Tensor, edges: torch.Tensor, degree: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        source, target = edges  # (E,) each
        e = e + self.edge_out(
            self.edge_self(e) + self.edge_source(h)[source] + self.edge_target(h)[target]
        )  # (E, H)
        incoming = torch.zeros_like(h).index_add_(0, target, e) / degree  # (N, H)
        return h + self.node(torch.cat([h, incoming], dim=1)), e


class SliceAttention(nn.Module):
    """Transolver's physics attention (Wu et al., 2024) per graph of a batch: nodes are
    softly assigned to ``slices`` learned clusters, (N, H) -> weights (N, M); each graph's
    slice tokens (its weighted node means, (B, M, H)) attend to each other; every node gets
    back its weights' mix of the attended tokens, (N, H). Linear in N, and the clusters are
    functions of the node state, not of the mesh, so a remeshed breast uses the same weights.
    """

    def __init__(self, hidden: int, slices: int, heads: int) -> None:
        super().__init__()
        self.slices = slices
        self.assign = nn.Linear(hidden, slices)
        self.norm = nn.LayerNorm(hidden)
        self.attention = nn.MultiheadAttention(hidden, heads, batch_first=True)

    def forward(self, h: torch.Tensor, graph: torch.Tensor, n_graphs: int) -> torch.Tensor:
        w = torch.softmax(self.assign(h), dim=1)  # (N, M)
        n, hidden = h.shape
        tokens = h.new_zeros(n_graphs, self.slices * hidden).index_add_(
            0, graph, (w[:, :, None] * h[:, None, :]).reshape(n, -1)
        )  # (B, M * H)
        mass = h.new_zeros(n_graphs, self.slices).index_add_(0, graph, w)  # (B, M)
        tokens = self.norm(tokens.view(n_graphs, self.slices, hidden) / (mass[..., None] + 1e-6))
        mixed, _ = self.attention(tokens, tokens, tokens, need_weights=False)  # (B, M, H)
        return torch.einsum("nm,nmh->nh", w, mixed[graph])  # (N, H)


def step_knots(n_steps: int, count: int) -> torch.Tensor:
    """``count`` step indices (K,) evenly spaced over ``0 .. n_steps - 1``, the last one
    included; the input shape counts as step -1, so the first knot is not step 0 unless
    ``count >= n_steps``."""
    grid = torch.linspace(-1.0, n_steps - 1.0, min(count, n_steps) + 1)[1:]
    return torch.unique(grid.round().long())


def interpolate_steps(
    start: torch.Tensor, values: torch.Tensor, knots: torch.Tensor, n_steps: int
) -> torch.Tensor:
    """A trajectory (T, N, 3) linear in the step index between its values (K, N, 3) at the
    sorted step indices ``knots`` (K,), the last one ``n_steps - 1``, and ``start`` (N, 3) at
    step -1 (the input shape)."""
    grid = torch.cat([knots.new_tensor([-1]), knots])  # (K + 1,)
    points = torch.cat([start[None], values])  # (K + 1, N, 3)
    t = torch.arange(n_steps, device=knots.device)
    i = (torch.searchsorted(grid, t, right=True) - 1).clamp(0, len(knots) - 1)  # (T,)
    w = ((t - grid[i]) / (grid[i + 1] - grid[i])).to(points.dtype)[:, None, None]  # (T, 1, 1)
    return points[i] + w * (points[i + 1] - points[i])  # (T, N, 3)


def compliance_gain(
    nodes: torch.Tensor,
    graph: torch.Tensor,
    conditions: torch.Tensor,
    pairs: Sequence[tuple[int, int]],
) -> torch.Tensor:
    """Each node's breast's linear-elastic compliance relative to the reference materials,
    (N, 1): ``exp(-sum_t f_t c_t)`` over the tissues t of ``pairs`` (a node input column of
    t's indicator, a condition column of t's log-modulus ratio ``c_t = log(E_t / E_t^ref)``),
    ``f_t`` the breast's fraction of t's nodes among them. Under a body load the displacement
    of a linear-elastic body scales as 1/E, so a decoder whose output is multiplied by it
    learns the displacement per unit compliance and extrapolates in stiffness as 1/E.
    """
    columns, condition_columns = (list(c) for c in zip(*pairs, strict=True))
    bits = nodes[:, columns]  # (N, K)
    counts = bits.new_zeros(len(conditions), len(columns)).index_add_(0, graph, bits)  # (B, K)
    fractions = counts / counts.sum(dim=1, keepdim=True).clamp_min(1.0)  # (B, K)
    log_modulus = (fractions * conditions[:, condition_columns]).sum(dim=1)  # (B,)
    return torch.exp(-log_modulus)[graph][:, None]  # (N, 1)


def scaled_into_range(
    conditions: torch.Tensor, bounds: torch.Tensor, columns: Sequence[int]
) -> torch.Tensor:
    """The conditions (B, C) a network trained inside ``bounds`` (2, C: low, high; infinite
    where unbounded) is shown: the log-moduli of ``columns`` (the tissues of the compliance
    gain) shifted by one common amount, the least that brings them all inside their bounds
    (half-way between the two closest shifts when none does), then every column clamped to
    its bounds.

    A common shift is a uniform scaling of those moduli, under which a linear-elastic body's
    displacement scales exactly as the inverse of the scale, as `compliance_gain` does: so a
    breast softer or stiffer than every training breast is predicted as the nearest trained
    breast of the same stiffness ratios, and the gain, taken on the breast's own moduli,
    carries the rest, instead of the network extrapolating in its inputs. Conditions inside
    the bounds are returned unchanged.
    """
    columns = list(columns)
    x = conditions[:, columns]  # (B, K)
    low, high = bounds[0, columns], bounds[1, columns]  # (K,)
    least = (low - x).max(dim=1).values  # (B,) the smallest shift that meets every low bound
    most = (high - x).min(dim=1).values  # (B,) the largest that meets every high bound
    shift = torch.where(
        least <= most, least.clamp_min(0.0) + most.clamp_max(0.0), (least + most) / 2
    )  # (B,) zero when already inside
    shifted = conditions.clone()
    shifted[:, columns] = x + shift[:, None]
    return torch.maximum(torch.minimum(shifted, bounds[1]), bounds[0])  # (B, C)


class MeshGraphNet(nn.Module):
    """Encode-process-decode over a breast's tetrahedral mesh (MeshGraphNets, Pfaff et al.
    2021) with a global path per block (`SliceAttention`), decoding every node's whole step
    trajectory in one pass.

    Inputs of a batch of B breasts with N nodes in all (`datamodules.graphs.batch_graphs`):
    ``nodes`` (N, Fn) whose first three columns are the normalised input coordinates,
    ``edges`` (2, E), ``graph`` (N,) each node's breast, ``steps`` (B, T, Fs) the per-step
    inputs (plates), ``node_steps`` (T, N, Fns) per node and step, ``conditions`` (B, C)
    (stiffness, friction, view). Output: coordinates (T, N, 3), the input coordinates plus a
    predicted displacement.

    The processor sees each breast's conditions and its last step's inputs (where the plates
    end); the decoder adds each step's embedding to each node's latent (and the node's
    heights against the plates at that step), so the whole trajectory costs one processor
    pass and a (T, N) grid of small MLP rows.

    Parameters
    ----------
    n_node, n_step, n_node_step, n_condition : int
        Fn, Fs, Fns, C.
    hidden : int
        Latent size of nodes and edges.
    layers : int
        Processor blocks.
    slices, heads : int
        Of each block's `SliceAttention`; ``slices=0``: no global path (plain MeshGraphNets).
    decoder_hidden : int
        Width of the per-(step, node) decoder.
    compliance : sequence of (int, int)
        Pairs (tissue indicator column of ``nodes``, log-modulus column of ``conditions``):
        the decoded displacement is multiplied by each breast's `compliance_gain` over these
        tissues; empty: not scaled.
    bounded : bool
        Show the network the conditions `scaled_into_range` of the buffer
        ``condition_bounds`` (2, C), infinite until set (the training breasts' range, by
        `mammo_net.module.MeshGraphModule.adapt`); needs ``compliance``, which then takes the
        breast's own conditions.
    """

    def __init__(
        self,
        n_node: int,
        n_step: int,
        n_node_step: int,
        n_condition: int,
        hidden: int,
        layers: int,
        slices: int,
        heads: int,
        decoder_hidden: int,
        compliance: Sequence[tuple[int, int]] = (),
        bounded: bool = False,
    ) -> None:
        super().__init__()
        self.compliance = tuple(compliance)
        if bounded and not self.compliance:
            raise ValueError("bounded conditions need the compliance gain (compliance=...)")
        self.bounded = bounded
        if bounded:
            unbounded = torch.tensor([-torch.inf, torch.inf])[:, None].expand(2, n_condition)
            self.register_buffer("condition_bounds", unbounded.clone())  # (2, C)
        self.node_encoder = mlp(n_node + n_condition + n_step, hidden, hidden)
        self.edge_encoder = mlp(4, hidden, hidden)
        self.blocks = nn.ModuleList(MessagePassing(hidden) for _ in range(layers))
        self.mixing = nn.ModuleList(
            SliceAttention(hidden, slices, heads) for _ in range(layers if slices else 0)
        )
        self.step_encoder = mlp(n_step + n_condition, decoder_hidden, decoder_hidden)
        self.node_head = nn.Linear(hidden, decoder_hidden)
        self.node_step_head = nn.Linear(n_node_step, decoder_hidden, bias=False)
        self.decoder = nn.Sequential(
            nn.SiLU(),
            nn.Linear(decoder_hidden, decoder_hidden),
            nn.SiLU(),
            nn.Linear(decoder_hidden, 3),
        )

    @property
    def gain_columns(self) -> list[int]:
        """The condition columns of the compliance gain's tissues (their log-moduli)."""
        return [column for _, column in self.compliance]

    def forward(
        self,
        nodes: torch.Tensor,
        edges: torch.Tensor,
        graph: torch.Tensor,
        steps: torch.Tensor,
        node_steps: torch.Tensor,
        conditions: torch.Tensor,
        decoded: torch.Tensor | None = None,
        knots: int | None = None,
    ) -> torch.Tensor:
        """Coordinates (T, N, 3), or (T', N, 3) at the step indices ``decoded`` (T',) only
        (training on a sample of the steps: the processor pass is the same). ``knots``: decode
        that many evenly spaced steps (`step_knots`) and interpolate the others linearly from
        the input coordinates (`interpolate_steps`), (T, N, 3) at a fraction of the decoder's
        cost; ignored with ``decoded``."""
        x = nodes[:, :3]  # (N, 3)
        n_steps = steps.shape[1]
        if decoded is None and knots is not None and knots < n_steps:
            decoded = step_knots(n_steps, knots).to(x.device)
            out = self(nodes, edges, graph, steps, node_steps, conditions, decoded)
            return interpolate_steps(x, out, decoded, n_steps)
        n_graphs = steps.shape[0]
        relative = x[edges[1]] - x[edges[0]]  # (E, 3)
        e = self.edge_encoder(torch.cat([relative, relative.norm(dim=1, keepdim=True)], 1))
        seen = conditions
        if self.bounded:
            seen = scaled_into_range(conditions, self.condition_bounds, self.gain_columns)
        context = torch.cat([seen, steps[:, -1]], dim=1)[graph]  # (N, C + Fs)
        h = self.node_encoder(torch.cat([nodes, context], dim=1))  # (N, H)
        degree = (
            torch.zeros_like(x[:, :1])
            .index_add_(0, edges[1], torch.ones_like(edges[1], dtype=x.dtype)[:, None])
            .clamp_min(1.0)
        )  # (N, 1)
        for k, block in enumerate(self.blocks):
            h, e = block(h, e, edges, degree)
            if self.mixing:
                h = h + self.mixing[k](h, graph, n_graphs)
        if decoded is not None:
            steps, node_steps = steps[:, decoded], node_steps[decoded]  # T' steps
        z = self.step_encoder(
            torch.cat([steps, seen[:, None].expand(-1, steps.shape[1], -1)], dim=-1)
        )  # (B, T, D)
        # (T, 1, D) broadcast for one breast (a prediction), else each node's breast's
        z = z.transpose(0, 1) if n_graphs == 1 else z.transpose(0, 1)[:, graph]
        a = self.node_head(h)[None] + z  # (T, N, D)
        if node_steps.shape[-1]:  # the unloaded state has no per-node step inputs
            a = a + self.node_step_head(node_steps)  # (T, N, D)
        displacement = self.decoder(a)  # (T, N, 3)
        if self.compliance:
            displacement = displacement * compliance_gain(
                nodes, graph, conditions, self.compliance
            )  # (T, N, 3) * (N, 1)
        return x[None] + displacement  # (T, N, 3)
