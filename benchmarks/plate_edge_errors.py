"""Where are a compression model's largest node errors? Near the plates' chest-side edge.

For each compression run folder (``predictions/<model>.npz``, predicted first from the run's
model files where missing, as the report does), per breast at the last recorded step: the
node errors against the FE (Euclidean distance, mm: sqrt 3 times the paper's per-node RMSE that
the report uses), raw and after `mammo_net.validity.ValidityProjection`, and,
for every node more than ``--threshold`` mm off in the raw prediction, its signed distance
to the upper plate's chest-side edge in the compression's first step (mm, along the plate's
in-plane axis away from the chest: negative behind the edge, over the chest-side tissue).

    python benchmarks/plate_edge_errors.py 'results/cv/mesh_gnn/compression/fold*' \
        'results/cv/xgboost/compression/fold*' --out /tmp/plate_edge.json
"""

from __future__ import annotations

import argparse
import glob
from pathlib import Path

import numpy as np

from datamodules.trajectories import TrajectoryDataModule
from fem.contract.atomic import write_json
from fem.contract.trajectory import Trajectory
from mammo_net.inference import load_predictions
from mammo_net.predictor import predict_run
from mammo_net.validity import ValidityProjection


def edge_distance(traj: Trajectory, nodes: np.ndarray) -> np.ndarray:
    """Signed distance (mm) of ``nodes`` at the compression's first step to the upper plate's
    chest-side edge, along the plate's in-plane axis away from the chest; shape (len(nodes),)."""
    origin, _, axis = traj.plates[0, 1]
    return (traj.compressed[0, nodes] - origin) @ axis


def breast_row(traj: Trajectory, predicted: np.ndarray, threshold: float) -> dict:
    """Last-step node errors of one breast's compression prediction ``predicted`` (T2, N, 3)."""
    projected = ValidityProjection().project_step(traj, "compression", predicted)
    raw = np.linalg.norm(predicted[-1] - traj.compressed[-1], axis=-1)
    after = np.linalg.norm(projected[-1] - traj.compressed[-1], axis=-1)
    bad = np.flatnonzero(raw > threshold)
    return {
        "max_raw_mm": float(raw.max()),
        "max_projected_mm": float(after.max()),
        "nodes_over": int(bad.size),
        "edge_distance_mm": edge_distance(traj, bad).tolist(),
        "compression_ratio": float(traj.compression_ratio[-1]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("runs", nargs="+", help="compression run folders or glob patterns")
    ap.add_argument("--threshold", type=float, default=10.0, help="a large node error, mm")
    ap.add_argument("--out", type=Path, default=None, help="per-breast rows as JSON")
    args = ap.parse_args()
    runs = [Path(r) for pattern in args.runs for r in sorted(glob.glob(pattern)) or [pattern]]
    rows: dict[str, dict[str, dict]] = {}
    for run in runs:
        predict_run(run)
        dm = TrajectoryDataModule.from_run(run)
        if dm.hparams.step != "compression":
            raise ValueError(f"{run}: step {dm.hparams.step!r}; this benchmark needs compression")
        for file in sorted((run / "predictions").glob("*.npz")):
            for name, predicted in load_predictions(file).items():
                traj = Trajectory.load(dm.source(name))
                row = breast_row(traj, predicted.transpose(1, 0, 2), args.threshold)
                rows.setdefault(file.stem, {})[name] = row
    t = args.threshold
    print(
        f"| model | breasts | max node error > {t:g} mm (raw) | > {2 * t:g} mm (raw) | nodes > {t:g}"
        f" mm | worst node, raw / projected (mm) | of those nodes, within 15 mm of the plate edge"
        " | their edge distance, median (mm) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for model, breasts in rows.items():
        r = list(breasts.values())
        d = np.concatenate([x["edge_distance_mm"] for x in r] + [np.zeros(0)])
        worst = max(breasts, key=lambda b: breasts[b]["max_raw_mm"])
        print(
            f"| {model} | {len(r)} | {sum(x['max_raw_mm'] > t for x in r)} |"
            f" {sum(x['max_raw_mm'] > 2 * t for x in r)} | {d.size} |"
            f" {breasts[worst]['max_raw_mm']:.1f} / {max(x['max_projected_mm'] for x in r):.1f}"
            f" ({worst}) | {np.mean(np.abs(d) <= 15) if d.size else float('nan'):.0%} |"
            f" {np.median(d) if d.size else float('nan'):.1f} |"
        )
    if args.out:
        write_json(rows, args.out)


if __name__ == "__main__":
    main()
