"""Time both FE steps per breast: the unloaded state and the compression with friction.

    python benchmarks/simulate_breast.py data/cohort/full/P0001_L.npz ... --repeats 5
    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 python benchmarks/simulate_breast.py ... --linear-solver pardiso
    python benchmarks/simulate_breast.py ... --poisson 0.4995 --repeats 1   # K/mu = 1000

For each mesh, ``--repeats`` runs of `fem.engine.simulation.Simulation` with the paper's parameters
(100 unloaded-state steps, 70 compression steps to the breast's target compression ratio,
Coulomb friction 0.25, gravity on) in this one process, so on one core. Prints per breast the
median wall time of each step and of both, the final compression ratio and the volume change,
then the median over the breasts. Use it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import statistics
from dataclasses import replace
from pathlib import Path

from fem.contract.trajectory import Trajectory
from fem.engine.simulation import PAPER_MATERIALS, Simulation, SimulationFailed


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("meshes", nargs="+", help="Trajectory .npz files from the cohort command")
    ap.add_argument("--repeats", type=int, default=5, help="runs per breast (median reported)")
    ap.add_argument("--friction", type=float, default=0.25)
    ap.add_argument("--linear-solver", default="auto", help="auto | superlu | pardiso")
    ap.add_argument(
        "--poisson",
        type=float,
        default=None,
        help="Poisson's ratio of every solid tissue (0.4995: K/mu = 1000; default the paper's)",
    )
    args = ap.parse_args()
    materials = dict(PAPER_MATERIALS)
    if args.poisson is not None:
        for name in ("fat", "gland", "muscle"):
            materials[name] = replace(materials[name], poisson=args.poisson)
    simulation = Simulation(
        materials=materials, friction=args.friction, linear_solver=args.linear_solver
    )
    totals = []
    print(
        "| breast | volume (cm^3) | elements | unloaded (s) | compression (s) | both (s) "
        "| CR | volume change |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in args.meshes:
        traj = Trajectory.load(path)
        runs = []
        try:
            for _ in range(args.repeats):
                result = simulation(traj)
                runs.append(result.metadata["simulation"])
        except SimulationFailed as exc:
            print(f"| {path} | failed: {exc} |", flush=True)
            continue
        unloaded = statistics.median(r["seconds"]["unloaded"] for r in runs)
        compression = statistics.median(r["seconds"]["compression"] for r in runs)
        both = statistics.median(sum(r["seconds"].values()) for r in runs)
        totals.append(both)
        print(
            f"| {Path(path).stem} | {traj.metadata.get('breast_volume_cm3', 0):.0f} "
            f"| {traj.n_cells} | {unloaded:.2f} | {compression:.2f} | {both:.2f} "
            f"| {runs[-1]['compression_ratio']:.2f} | {100 * runs[-1]['volume_change']:+.2f} % |",
            flush=True,
        )
    if totals:
        print(
            f"\nmedian over {len(totals)} breasts of the median of {args.repeats} runs: "
            f"{statistics.median(totals):.2f} s per breast (both steps)"
        )


if __name__ == "__main__":
    main()
