"""Time both FE steps on cohort breasts (first version; issue 3 adds repeats and friction).

    python benchmarks/simulate_breast.py data/cohort/full/P0001_L.npz data/cohort/full/P0002_R.npz

For each mesh: the unloaded state (100 recorded steps) and the frictionless compression to the
phantom's compressed thickness (70 recorded steps), with wall times, the final compression
ratio and the volume change.
"""

from __future__ import annotations

import argparse
import time

from fem.quality import signed_volume
from fem.simulate import compression, unloaded_state
from fem.solver import SolverError
from fem.trajectory import Trajectory


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("meshes", nargs="+", help="Trajectory .npz files from the cohort command")
    args = ap.parse_args()
    for path in args.meshes:
        traj = Trajectory.load(path)
        t0 = time.perf_counter()
        unloaded = unloaded_state(traj, n_steps=100)
        t1 = time.perf_counter()
        line = f"{path}: {traj.metadata.get('breast_volume_cm3', float('nan')):.0f} cm^3, unloaded {t1 - t0:.1f} s"
        try:
            result = compression(
                traj, unloaded[-1], traj.metadata["compressed_thickness_mm"], n_steps=70
            )
        except SolverError as exc:
            print(
                f"{line}, compression FAILED after {time.perf_counter() - t1:.1f} s: {exc}",
                flush=True,
            )
            continue
        volume = (
            signed_volume(result.positions[-1], traj.cells).sum()
            / signed_volume(unloaded[-1], traj.cells).sum()
        )
        print(
            f"{line}, compression {time.perf_counter() - t1:.1f} s, compression ratio "
            f"{result.compression_ratio[-1]:.2f}, volume change {100 * (volume - 1):+.2f} %",
            flush=True,
        )


if __name__ == "__main__":
    main()
