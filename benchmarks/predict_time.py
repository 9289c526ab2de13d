"""Prediction time per breast with `mammo_net.predictor.predict_breast`: features, the
unloaded-state model, plate placement and the compression model, for one thickness and for a
batched sweep of thicknesses.

    python benchmarks/predict_time.py data/cohort/full/trajectories/P0001_L.npz ... \
        --unloaded <run>/checkpoints/last.ckpt --compression <run>/baselines/xgboost.json

Each breast is predicted ``--repeats`` times after one untimed warm-up call; prints the median
wall time per breast for one thickness (the FE's) and per thickness in a sweep of
``--sweep`` thicknesses (80-100 % of the FE thickness) in one call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from fem.trajectory import Trajectory
from mammo_net.predictor import load_surrogate, predict_breast


def timed(repeats: int, call, *args) -> float:
    """Median wall time of ``call(*args)`` over ``repeats`` runs after one warm-up run, s."""
    call(*args)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call(*args)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("breasts", nargs="+", help="simulated trajectories (.npz)")
    ap.add_argument("--unloaded", required=True, help="model file of the unloaded-state step")
    ap.add_argument("--compression", required=True, help="model file of the compression step")
    ap.add_argument("--sweep", type=int, default=20, help="thicknesses in the batched call")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    unloaded = load_surrogate(args.unloaded, "unloaded")
    compression = load_surrogate(args.compression, "compression")
    single, swept = [], []
    for path in args.breasts:
        traj = Trajectory.load(path)
        fe = float(traj.metadata["simulation"]["compressed_thickness_mm"])
        sweep = np.linspace(0.8 * fe, fe, args.sweep)  # thinner: always below the breast
        models = (traj, unloaded, compression)
        single.append(timed(args.repeats, predict_breast, *models, [fe]))
        swept.append(timed(args.repeats, predict_breast, *models, sweep) / args.sweep)
        print(
            f"{traj.metadata.get('source', path)}: {traj.n_nodes} nodes, one thickness "
            f"{1e3 * single[-1]:.1f} ms, sweep of {args.sweep} {1e3 * swept[-1]:.1f} ms each"
        )
    print(
        f"{unloaded.name} + {compression.name}, {torch.get_num_threads()} torch threads: "
        f"median {1e3 * statistics.median(single):.1f} ms per breast (whole trajectory, one "
        f"thickness); {1e3 * statistics.median(swept):.1f} ms per thickness in a sweep of "
        f"{args.sweep}"
    )


if __name__ == "__main__":
    main()
