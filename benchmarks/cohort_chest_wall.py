"""Where a simulated cohort's tissue ends up at the chest wall and under the plates.

    python benchmarks/cohort_chest_wall.py data/cohort/full/trajectories \
        --out results/fem/cohort_chest_wall.json

For every simulated breast (``P*.npz`` with compression steps) in the folder: the largest node
motion of the compression step, the deepest node below the lower plate's plane at the last
step (mm; positive: below it, which only nodes behind the plate's chest-side edge can be),
and the largest motion of the chest-wall nodes (`fem.engine.boundary.chest_wall_nodes`) in the
compression and in the unloaded state. Prints the cohort's counts and the breasts named with
``--show``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fem.contract.atomic import write_json
from fem.contract.trajectory import Trajectory
from fem.engine.boundary import chest_wall_nodes


def chest_wall_figures(traj: Trajectory) -> dict[str, float]:
    """The four figures of the module docstring for one simulated breast, mm."""
    start, end = traj.unloaded[-1], traj.compressed[-1]
    origin, normal, _ = traj.plates[-1, 0]
    wall = chest_wall_nodes(traj)
    return {
        "largest_motion_mm": float(np.linalg.norm(end - start, axis=1).max()),
        "deepest_below_lower_plate_mm": float((-(end - origin) @ normal).max()),
        "largest_wall_slide_mm": float(np.linalg.norm(end[wall] - start[wall], axis=1).max()),
        "largest_unloaded_wall_slide_mm": float(
            np.linalg.norm(start[wall] - traj.points[wall], axis=1).max()
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="folder of simulated trajectories")
    parser.add_argument("--out", type=Path, help="JSON of the figures per breast")
    parser.add_argument("--show", nargs="*", default=["P0212_R", "P0006_R", "P0075_R"])
    args = parser.parse_args()
    rows = {}
    for path in sorted(args.folder.glob("P*.npz")):
        traj = Trajectory.load(path)
        if len(traj.compressed) and len(traj.unloaded):
            rows[path.stem] = chest_wall_figures(traj)
    if not rows:
        raise SystemExit(f"{args.folder}: no simulated trajectories (P*.npz with both steps)")
    below = np.array([r["deepest_below_lower_plate_mm"] for r in rows.values()])
    slide = np.array([r["largest_wall_slide_mm"] for r in rows.values()])
    print(
        f"{len(rows)} breasts: a node > 10 mm below the lower plate in {(below > 10).sum()}, "
        f"> 50 mm in {(below > 50).sum()}, deepest {below.max():.1f} mm; largest wall slide "
        f"median {np.median(slide):.1f} mm, max {slide.max():.1f} mm"
    )
    for name in args.show:
        if name in rows:
            print(name, {k: round(v, 1) for k, v in rows[name].items()})
    if args.out:
        write_json(rows, args.out)


if __name__ == "__main__":
    main()
