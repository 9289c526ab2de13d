"""Time per breast of phantom generation, meshing and writing, on one core.

    python benchmarks/cohort_meshing.py --breasts 20 --repeats 5

Prints the median over repeats of the mean time per breast for each stage, and the median
per-breast total; figures go to docs/benchmarks.md by hand with the machine description.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from fem.breasts.figures import breast_sections_png
from fem.breasts.io import write_mesh
from fem.breasts.mesh import Mesher
from fem.breasts.phantom import PhantomGenerator


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--breasts", type=int, default=20, help="breasts per repeat (patients 0..n/2)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    generator, mesher = PhantomGenerator(seed=args.seed), Mesher()
    jobs = [(p, lat) for p in range(args.breasts // 2 + 1) for lat in "LR"][: args.breasts]
    stages = {"phantom": [], "mesh": [], "write": [], "png": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            times = {k: [] for k in stages}
            for p, lat in jobs:
                t0 = time.perf_counter()
                volume, meta = generator.breast(p, lat)
                t1 = time.perf_counter()
                traj = mesher(volume, meta)
                t2 = time.perf_counter()
                write_mesh(traj, Path(tmp) / "b.vtu")
                traj.save(Path(tmp) / "b.npz")
                t3 = time.perf_counter()
                breast_sections_png(traj, Path(tmp) / "b.png", volume)
                t4 = time.perf_counter()
                for k, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                    times[k].append(dt)
            for k in stages:
                stages[k].append(float(np.mean(times[k])))
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one process"
    )
    print(
        f"{len(jobs)} breasts x {args.repeats} repeats; seconds per breast (median of repeat means):"
    )
    for k, v in stages.items():
        print(f"  {k:8s} {np.median(v):.3f}  (repeats: {', '.join(f'{x:.3f}' for x in v)})")
    total = np.sum([np.asarray(v) for v in stages.values()], axis=0)
    print(f"  {'total':8s} {np.median(total):.3f}")
    print(f"516 breasts on 2 workers would take about {516 * np.median(total) / 2 / 60:.1f} min")


if __name__ == "__main__":
    main()
