"""Prediction time of the graph model per architecture, both steps of one breast: the cost of
a design before any training (the weights do not change it, so untrained networks of each
size are timed). Each architecture predicts each breast once after a warm-up call, the
architectures interleaved over ``--rounds`` rounds so that a slower spell of a shared machine
reaches all of them; the table gives the median and the first quartile over rounds and breasts.

    python benchmarks/graph_cost.py data/cohort/full/trajectories/P010[0-4]_L.npz \
        --architectures 8x64 4x48 4x32 0x32 --rounds 7

An architecture ``LxH`` is ``layers`` x ``hidden`` (the decoder ``H`` wide too; slices and heads
as `mammo_net.module.MeshGraphModule`'s defaults); ``0xH`` is the cost of everything but the
processor blocks (inputs, plates, encoders, decoder at the knots).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from datamodules.features import FeatureSchema
from datamodules.graphs import graph_inputs
from fem.contract.trajectory import Trajectory
from mammo_net.module import MeshGraphModule
from mammo_net.predictor import Surrogate, predict_breast

#: Recorded steps of the cohort's two simulation steps.
STEPS = {"unloaded": 100, "compression": 70}


def untrained(step: str, layers: int, hidden: int) -> tuple[Surrogate, int]:
    """An untrained graph model of ``step`` with ``layers`` blocks of width ``hidden``, and its
    number of parameters."""
    model = MeshGraphModule(step, hidden=hidden, layers=layers, decoder_hidden=hidden).eval()
    schema = FeatureSchema.current(step, graph_inputs(step), STEPS[step])
    n = sum(p.numel() for p in model.parameters())
    return Surrogate(model.name, schema, model.predictor(), graph=True), n


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("breasts", nargs="+", help="simulated trajectories (.npz)")
    ap.add_argument("--architectures", nargs="+", default=["8x64", "4x48", "4x32", "0x32"])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    breasts = [Trajectory.load(p) for p in args.breasts]
    models, sizes = {}, {}
    for a in args.architectures:
        layers, hidden = map(int, a.split("x"))
        (unloaded, n1), (compression, n2) = (untrained(s, layers, hidden) for s in STEPS)
        models[a], sizes[a] = (unloaded, compression), n1 + n2
    print(
        f"{len(breasts)} breasts, {min(b.n_nodes for b in breasts)}-"
        f"{max(b.n_nodes for b in breasts)} nodes; torch threads {torch.get_num_threads()}; "
        f"{args.rounds} rounds\n"
    )
    seconds: dict[str, list[float]] = {a: [] for a in models}
    for _ in range(args.rounds):
        for a, (unloaded, compression) in models.items():
            for traj in breasts:
                thickness = [float(traj.metadata["simulation"]["compressed_thickness_mm"])]
                predict_breast(traj, unloaded, compression, thickness)  # warm-up
                start = time.perf_counter()
                predict_breast(traj, unloaded, compression, thickness)
                seconds[a].append(time.perf_counter() - start)
    print("| layers x width | parameters, both steps | ms per breast, median | first quartile |")
    print("| --- | --- | --- | --- |")
    for a, s in seconds.items():
        print(
            f"| {a} | {sizes[a]:,} | {1e3 * statistics.median(s):.1f} | "
            f"{1e3 * np.percentile(s, 25):.1f} |"
        )


if __name__ == "__main__":
    main()
