"""Simple reversal against the inverse (backward-displacement) unloaded state on cohort breasts.

    nice -n 10 python benchmarks/inverse_unloaded.py                      # 12 breasts, spread
    nice -n 10 python benchmarks/inverse_unloaded.py data/cohort/full/P0001_L.npz ...

Without arguments: 12 breasts of ``data/cohort/full`` evenly spread over the volume ranks
(smallest to largest). For each breast: the simple reversal ``unloaded_state(...)[-1]``
(100 recorded steps, as in `fem.simulate`), the inverse ``inverse_unloaded_state`` (tolerance
0.01 mm, Aitken relaxation), their wall times, the number of fixed-point updates, the max and
mean node distance between the two unloaded shapes, the largest sag ``|x_img - X|`` of each,
and the misfit of the simple reversal: the largest node distance between the imaged shape and
the reversal shape loaded again by prone gravity (the inverse's misfit is below tolerance).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from fem.contract.trajectory import Trajectory
from fem.engine.boundary import chest_wall
from fem.engine.constraints import NodeFrames
from fem.engine.inverse import (
    InverseError,
    forward,
    inverse_unloaded_state,
    max_node_distance,
    prone_gravity,
)
from fem.engine.simulation import PAPER_MATERIALS, unloaded_state
from fem.engine.solver import SolverError

COHORT = Path("data/cohort/full")


def breast_volume(path: Path) -> float:
    """Breast volume, cm^3, from the archive's metadata (without loading the mesh)."""
    with np.load(path, allow_pickle=False) as data:
        return float(json.loads(str(data["metadata"])).get("breast_volume_cm3", float("nan")))


def volume_spread(directory: Path, count: int) -> list[Path]:
    """``count`` archives evenly spread over the volume ranks of the archives in ``directory``."""
    paths = sorted(directory.glob("*.npz"))
    if not paths:
        raise FileNotFoundError(f"{directory}: no .npz trajectories (run the cohort command)")
    ranked = sorted(paths, key=breast_volume)
    picks = np.unique(np.linspace(0, len(ranked) - 1, count).round().astype(int))
    return [ranked[i] for i in picks]


def compare(path: Path, tolerance: float, n_steps: int) -> dict[str, float | int | str]:
    """Both unloaded states of one breast and their distances (mm) and times (s)."""
    traj = Trajectory.load(path)
    t0 = time.perf_counter()
    simple = unloaded_state(traj, PAPER_MATERIALS, n_steps=n_steps)[-1]
    t1 = time.perf_counter()
    result = inverse_unloaded_state(traj, PAPER_MATERIALS, tolerance=tolerance)
    t2 = time.perf_counter()
    frames = NodeFrames.build(traj.n_nodes, chest_wall(traj, traj.points))
    reloaded = forward(traj, simple, frames, PAPER_MATERIALS, 10, prone_gravity())
    distance = np.linalg.norm(simple - result.points, axis=1)
    return {
        "breast": path.stem,
        "volume": float(traj.metadata.get("breast_volume_cm3", float("nan"))),
        "iterations": result.iterations,
        "converged": "yes" if result.converged else "NO",
        "residual": result.residuals[-1],
        "t_simple": t1 - t0,
        "t_inverse": t2 - t1,
        "max_distance": float(distance.max()),
        "mean_distance": float(distance.mean()),
        "sag_simple": max_node_distance(traj.points, simple),
        "sag_inverse": max_node_distance(traj.points, result.points),
        "misfit_simple": max_node_distance(reloaded, traj.points),
    }


HEADER = (
    "| breast | volume (cm^3) | updates | converged (final misfit, mm) | reversal time (s) | "
    "inverse time (s) | max distance (mm) | mean distance (mm) | max sag reversal (mm) | "
    "max sag inverse (mm) | reversal misfit (mm) |\n" + "| --- " * 11 + "|"
)


def row(r: dict) -> str:
    """One Markdown table row of `compare`'s result."""
    return (
        f"| {r['breast']} | {r['volume']:.0f} | {r['iterations']} | {r['converged']} "
        f"({r['residual']:.4f}) | {r['t_simple']:.1f} | {r['t_inverse']:.1f} | "
        f"{r['max_distance']:.2f} | {r['mean_distance']:.2f} | {r['sag_simple']:.1f} | "
        f"{r['sag_inverse']:.1f} | {r['misfit_simple']:.2f} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("meshes", nargs="*", type=Path, help="Trajectory .npz files")
    ap.add_argument("--count", type=int, default=12, help="breasts when no mesh is given")
    ap.add_argument("--tolerance", type=float, default=0.01, help="inverse tolerance, mm")
    ap.add_argument("--steps", type=int, default=100, help="recorded steps of the reversal")
    args = ap.parse_args()
    paths = args.meshes or volume_spread(COHORT, args.count)
    print(HEADER, flush=True)
    results = []
    for path in paths:
        try:
            r = compare(path, args.tolerance, args.steps)
        except (InverseError, SolverError) as exc:
            print(f"| {path.stem} | FAILED: {exc} |", flush=True)
            continue
        results.append(r)
        print(row(r), flush=True)
    if results:
        maxima = [r["max_distance"] for r in results]
        means = [r["mean_distance"] for r in results]
        ratio = [r["max_distance"] / r["sag_inverse"] for r in results]
        print(
            f"\n{len(results)} of {len(paths)} breasts; max node distance reversal-inverse: "
            f"median {statistics.median(maxima):.2f} mm, max {max(maxima):.2f} mm; mean node "
            f"distance: median {statistics.median(means):.2f} mm, max {max(means):.2f} mm; "
            f"max distance / max inverse sag: median {100 * statistics.median(ratio):.0f} %, "
            f"max {100 * max(ratio):.0f} %; converged {sum(r['converged'] == 'yes' for r in results)}"
        )


if __name__ == "__main__":
    main()
