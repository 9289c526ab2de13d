"""Prediction time per breast with `mammo_net.predictor.predict_breast`: features, the
unloaded-state model, plate placement and the compression model (the whole trajectory: every
recorded step of both simulation steps), for one thickness and per thickness in a batched
sweep, for each model.

    python benchmarks/predict_time.py data/cohort/full/trajectories/P0001_L.npz ... \
        --model att_blstm <run>/checkpoints/last.ckpt <run>/checkpoints/last.ckpt \
        --model xgboost <unloaded run>/baselines/xgboost.json <run>/baselines/xgboost.json \
        --model ert <unloaded run>/baselines/ert.npz <run>/baselines/ert.npz --row-by-row

Each breast is predicted ``--repeats`` times after one untimed warm-up call; the table gives
the median over breasts of each breast's median wall time. ``--row-by-row`` also times the
tree models' own row-by-row predictions (XGBoost's and scikit-learn's), which the step-interval
traversal (`mammo_net.sequence_trees`) replaces; ``--bf16`` also times the networks in
``bf16-mixed`` precision; ``--projection`` also times `mammo_net.validity.ValidityProjection`
(predict.py's default) on the one-thickness prediction and counts the inverted elements over
all predicted steps before it and after it.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numba
import numpy as np
import torch

from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from mammo_net.predictor import BreastShapes, load_surrogate, predict_breast
from mammo_net.validity import ValidityProjection


def timed(repeats: int, call, *args) -> float:
    """Median wall time of ``call(*args)`` over ``repeats`` runs after one warm-up run, s."""
    call(*args)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call(*args)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def inverted(traj: Trajectory, shapes: BreastShapes) -> int:
    """Inverted elements (signed volume <= 0) summed over every predicted step."""
    steps = [*shapes.unloaded, *shapes.compressed.reshape(-1, traj.n_nodes, 3)]
    return int(sum((signed_volume(x.astype(np.float64), traj.cells) <= 0).sum() for x in steps))


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("breasts", nargs="+", help="simulated trajectories (.npz)")
    ap.add_argument(
        "--model", nargs=3, action="append", required=True,
        metavar=("NAME", "UNLOADED", "COMPRESSION"), help="a model's files of both steps",
    )  # fmt: skip
    ap.add_argument("--row-by-row", action="store_true", help="also the trees' row predictions")
    ap.add_argument("--bf16", action="store_true", help="also the networks in bf16-mixed")
    ap.add_argument("--projection", action="store_true", help="also the validity projection")
    ap.add_argument("--sweep", type=int, default=20, help="thicknesses in the batched call")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    breasts = [Trajectory.load(p) for p in args.breasts]
    variants = []
    for name, unloaded, compression in args.model:
        variants.append((name, unloaded, compression, {}))
        network = unloaded.endswith(".ckpt")
        if args.row_by_row and not network:
            variants.append((f"{name} (row by row)", unloaded, compression, {"row_by_row": True}))
        if args.bf16 and network:
            variants.append((f"{name} (bf16)", unloaded, compression, {"precision": "bf16-mixed"}))
    print(
        f"{len(breasts)} breasts, {min(b.n_nodes for b in breasts)}-"
        f"{max(b.n_nodes for b in breasts)} nodes, {min(len(b.cells) for b in breasts)}-"
        f"{max(len(b.cells) for b in breasts)} tetrahedra; torch threads "
        f"{torch.get_num_threads()}, numba threads {numba.get_num_threads()}; median of "
        f"{args.repeats} runs per breast, median over breasts\n"
    )
    header = f"| model | one thickness (ms) | per thickness, sweep of {args.sweep} (ms) |"
    if args.projection:
        header += " projection (ms) | inverted elements, all steps, before / after |"
    print(header)
    print("|" + " --- |" * header.count(" |"))
    for name, unloaded_file, compression_file, options in variants:
        unloaded = load_surrogate(unloaded_file, "unloaded", **options)
        compression = load_surrogate(compression_file, "compression", **options)
        single, swept, projected, before, after = [], [], [], 0, 0
        for traj in breasts:
            fe = float(traj.metadata["simulation"]["compressed_thickness_mm"])
            sweep = np.linspace(0.8 * fe, fe, args.sweep)  # thinner: always below the breast
            models = (traj, unloaded, compression)
            single.append(timed(args.repeats, predict_breast, *models, [fe]))
            swept.append(timed(max(1, args.repeats // 2), predict_breast, *models, sweep))
            if args.projection:
                shapes = predict_breast(*models, [fe])
                projection = ValidityProjection()
                projected.append(timed(max(1, args.repeats // 2), projection, traj, shapes))
                before += inverted(traj, shapes)
                after += inverted(traj, projection(traj, shapes)[0])
        row = (
            f"| {name} | {1e3 * statistics.median(single):.1f} | "
            f"{1e3 * statistics.median(swept) / args.sweep:.1f} |"
        )
        if args.projection:
            row += f" {1e3 * statistics.median(projected):.0f} | {before} / {after} |"
        print(row, flush=True)


if __name__ == "__main__":
    main()
