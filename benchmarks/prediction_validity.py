"""Are a run's predicted shapes physically valid, and what does the validity projection cost
them? For each model of each run folder (``predictions/<model>.npz``, the validation breasts of
its split, predicted first from the run's model files where missing, as the report does), per
breast: inverted elements (signed volume <= 0) over all predicted steps and at
the last step, skin nodes deeper than 0.5 mm inside a plate (compression), then the same after
`mammo_net.validity.ValidityProjection` (predict.py's default, or another
``--min-volume-ratio``), its wall time and the RMSE
against the FE (all recorded steps and the last one) before and after it.

    python benchmarks/prediction_validity.py results/cv/mesh_gnn/compression/fold0 \
        results/cv/xgboost/compression/fold0 --out /tmp/validity.json

The unloaded-state runs project the predicted unloaded steps; the compression runs take the
FE's unloaded state as the compression's start (the models of one step are judged alone).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from datamodules.trajectories import TrajectoryDataModule
from fem.contract.projection import plate_depth
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Trajectory
from mammo_net.inference import load_predictions
from mammo_net.metrics import breast_rmse
from mammo_net.predictor import BreastShapes, predict_run
from mammo_net.validity import ValidityProjection, step_shapes

#: Depth inside a plate from which a skin node counts as penetrating, mm (`PhysicalChecks`).
PLATE_TOLERANCE_MM = 0.5


def violations(traj: Trajectory, step: str, shapes: BreastShapes) -> dict[str, int]:
    """Inverted elements over all steps and at the last one, and penetrating skin nodes."""
    steps = shapes.unloaded if step == "unloaded" else shapes.compressed[0]
    volume = signed_volume(steps.astype(np.float64), traj.cells)  # (T, E)
    out = {
        "inverted_all_steps": int((volume <= 0).sum()),
        "inverted_last_step": int((volume[-1] <= 0).sum()),
        "penetrating_nodes": 0,
    }
    if step == "compression":
        skin = traj.flagged(NodeFlag.SKIN)
        out["penetrating_nodes"] = int(
            sum(
                (plate_depth(x.astype(np.float64), skin, p) > PLATE_TOLERANCE_MM).sum()
                for x, p in zip(steps, shapes.plates[0], strict=True)
            )
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("runs", nargs="+", help="train.py run folders (predictions/ or model files)")
    ap.add_argument("--limit", type=int, default=None, help="the first breasts only")
    ap.add_argument("--out", type=Path, default=None, help="per-breast rows as JSON")
    ap.add_argument(
        "--min-volume-ratio", type=float, default=ValidityProjection.min_volume_ratio,
        help="the projection's smallest element volume / reference volume",
    )  # fmt: skip
    args = ap.parse_args()
    projection = ValidityProjection(min_volume_ratio=args.min_volume_ratio)
    rows = []
    print(
        "| run | model | breasts | with inverted elements, before / after | inverted, all steps,"
        " before / after | penetrating skin nodes, before / after | projection (ms, median)"
        " | all-steps RMSE before / after (mm, mean) | last-step RMSE before / after (mm, mean) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for run in map(Path, args.runs):
        predict_run(run)  # the missing predictions/<model>.npz, from the run's model files
        dm = TrajectoryDataModule.from_run(run)
        step = dm.hparams.step
        for file in sorted((run / "predictions").glob("*.npz")):
            predictions = load_predictions(file)
            names = sorted(predictions)[: args.limit]
            model_rows = []
            for name in names:
                traj = Trajectory.load(dm.source(name))
                truth = traj.unloaded if step == "unloaded" else traj.compressed
                shapes = step_shapes(traj, step, predictions[name].transpose(1, 0, 2))
                start = time.perf_counter()
                projected, _ = projection(traj, shapes)
                seconds = time.perf_counter() - start
                after = projected.unloaded if step == "unloaded" else projected.compressed[0]
                before = shapes.unloaded if step == "unloaded" else shapes.compressed[0]
                rmse = [
                    breast_rmse(x.transpose(1, 0, 2), truth.transpose(1, 0, 2))
                    for x in (before, after)
                ]
                model_rows.append(
                    {
                        "run": str(run),
                        "model": file.stem,
                        "breast": name,
                        "before": violations(traj, step, shapes),
                        "after": violations(traj, step, projected),
                        "projection_s": seconds,
                        "rmse_all_steps_mm": [r["all_steps"] for r in rmse],
                        "rmse_last_step_mm": [r["last_step"] for r in rmse],
                    }
                )
            rows += model_rows

            def total(when: str, key: str, rows=model_rows) -> int:
                return sum(r[when][key] for r in rows)

            def breasts(when: str, rows=model_rows) -> int:
                return sum(r[when]["inverted_all_steps"] > 0 for r in rows)

            ms = 1e3 * statistics.median(r["projection_s"] for r in model_rows)
            every = np.mean([r["rmse_all_steps_mm"] for r in model_rows], axis=0)
            last = np.mean([r["rmse_last_step_mm"] for r in model_rows], axis=0)
            print(
                f"| {run} | {file.stem} | {len(model_rows)} | {breasts('before')} / "
                f"{breasts('after')} | {total('before', 'inverted_all_steps')} / "
                f"{total('after', 'inverted_all_steps')} | "
                f"{total('before', 'penetrating_nodes')} / {total('after', 'penetrating_nodes')}"
                f" | {ms:.0f} | {every[0]:.3f} / {every[1]:.3f} | {last[0]:.3f} / {last[1]:.3f} |",
                flush=True,
            )
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
