"""Real-size meshes: one breast meshed at several sizes through both FE steps.

    python benchmarks/fem_sizes.py --breast P0001_L --elements 2250 10000 40000 100000 \
        --out results/fem/sizes.json
    python benchmarks/fem_sizes.py --elements 10000 40000 --steps 20 20 --against 100 70

The breast's segmentation (the cohort's generator) is meshed with ``target_elements`` set to
each size (`fem.breasts.mesh.Mesher`, tolerance a ninth of it) and simulated with the paper's
settings (`fem.engine.simulation.Simulation`: ``--steps`` recorded unloaded-state and
compression steps, by default the paper's 100 and 70, to the breast's target ratio, friction
``--friction``, by default the paper's 0.25 (0: frictionless, what friction costs), skin
membrane, sliding chest wall, cc view) and ``--linear-solver``. ``--against U C``
also runs each mesh with U and C steps (untimed in the table) and reports how far the two final
compressed shapes lie apart (RMS and maximum node distance, mm): what fewer recorded steps, a
registration's choice, cost in accuracy (friction makes the answer depend on the load path). Each size runs in a fresh process, so its peak resident memory is its
own; Newton iterations, tangent assemblies and factorizations are counted by wrapping the
engine's functions. Prints a table and the exponent ``b`` of the fit ``time = a n^b`` over the
sizes (n: tetrahedra).
"""

from __future__ import annotations

import argparse
import platform
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from hydra.utils import instantiate
from omegaconf import OmegaConf

import fem.engine.solver as solver
from fem import CONFIG_DIR
from fem.contract.atomic import write_json
from fem.engine.constraints import FramedModel
from fem.engine.linear import resolve_backend
from fem.engine.simulation import FRICTION, Simulation, SimulationFailed


def counted(counts: dict[str, int]) -> None:
    """Wrap Newton, the framed tangent and the factorization so that they count into ``counts``."""
    newton, tangent, factorize = (
        solver.newton,
        FramedModel.tangent,
        solver.ReusedFactorization._factorize,
    )

    def newton_counted(*args, **kwargs):
        out = newton(*args, **kwargs)
        counts["newton_iterations"] += out[1]
        return out

    def tangent_counted(self, y):
        counts["tangents"] += 1
        return tangent(self, y)

    def factorize_counted(self, A):
        counts["factorizations"] += 1
        return factorize(self, A)

    solver.newton = newton_counted
    FramedModel.tangent = tangent_counted
    solver.ReusedFactorization._factorize = factorize_counted


def run(
    name: str,
    elements: int,
    linear_solver: str,
    steps: tuple[int, int] = (100, 70),
    friction: float = FRICTION,
) -> dict:
    """Mesh ``name`` at about ``elements`` tetrahedra and simulate both steps with ``steps``
    recorded (unloaded, compression) steps and the plates' Coulomb ``friction`` (in a worker);
    the row and the final compressed shape (N, 3) under ``"final"``."""
    generator = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "generator" / "default.yaml"))
    mesher = OmegaConf.load(Path(CONFIG_DIR) / "mesher" / "default.yaml")
    mesher.target_elements, mesher.tolerance = elements, max(elements // 9, 250)
    volume, meta = generator.breast(int(name[1:5]), name[-1])
    traj = instantiate(mesher)(volume, meta)
    counts = {"newton_iterations": 0, "tangents": 0, "factorizations": 0}
    counted(counts)
    row = {
        "breast": name,
        "target_elements": elements,
        "tetrahedra": traj.n_cells,
        "dofs": 3 * traj.n_nodes,
        "linear_solver": resolve_backend(linear_solver, 3 * traj.n_nodes),
        "steps": list(steps),
        "friction": friction,
    }
    t0 = time.perf_counter()
    try:
        result = Simulation(
            linear_solver=linear_solver,
            unloaded_steps=steps[0],
            compression_steps=steps[1],
            friction=friction,
        )(traj)
    except SimulationFailed as exc:
        return {**row, "failed": str(exc), "seconds": time.perf_counter() - t0, **counts}
    info = result.metadata["simulation"]
    return {
        **row,
        "seconds": time.perf_counter() - t0,
        "unloaded_s": info["seconds"]["unloaded"],
        "compression_s": info["seconds"]["compression"],
        **counts,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "volume_change": info["volume_change"],
        "min_element_volume_ratio": info["min_element_volume_ratio"],
        "compression_ratio": info["compression_ratio"],
        "final": result.compressed[-1],
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--breast", default="P0001_L")
    ap.add_argument("--elements", nargs="+", type=int, default=[2250, 10000, 40000, 100000])
    ap.add_argument("--linear-solver", default="auto", help="auto | superlu | pardiso")
    ap.add_argument("--steps", nargs=2, type=int, default=[100, 70], metavar=("U", "C"))
    ap.add_argument("--against", nargs=2, type=int, default=None, metavar=("U", "C"))
    ap.add_argument("--friction", type=float, default=FRICTION, help="0: frictionless")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    print(
        "| tetrahedra | DOFs | solver | steps | unloaded (s) | compression (s) | both (s) | Newton "
        "iterations | tangents | factorizations | peak memory (MB) | volume change "
        "| from the --against answer, RMS / max (mm) |"
    )
    print("| --- " * 13 + "|")
    for elements in args.elements:
        row = in_fresh_process(args.breast, elements, args.linear_solver, args.steps, args.friction)
        if args.against and "failed" not in row:
            other = in_fresh_process(
                args.breast, elements, args.linear_solver, args.against, args.friction
            )
            if "failed" not in other:
                d = np.linalg.norm(row["final"] - other["final"], axis=1)
                row["against"] = {
                    "steps": list(args.against),
                    "seconds": other["seconds"],
                    "rms_mm": float(np.sqrt(np.mean(d**2))),
                    "max_mm": float(d.max()),
                }
        row.pop("final", None)
        rows.append(row)
        if "failed" in row:
            print(f"| {row['tetrahedra']} | failed after {row['seconds']:.0f} s: {row['failed']} |")
        else:
            against = row.get("against")
            print(
                f"| {row['tetrahedra']} | {row['dofs']} | {row['linear_solver']} "
                f"| {row['steps'][0]}/{row['steps'][1]} "
                f"| {row['unloaded_s']:.1f} | {row['compression_s']:.1f} | {row['seconds']:.1f} "
                f"| {row['newton_iterations']} | {row['tangents']} | {row['factorizations']} "
                f"| {row['peak_memory_mb']:.0f} | {100 * row['volume_change']:+.2f} % "
                + (
                    f"| {against['rms_mm']:.3f} / {against['max_mm']:.3f} |" if against else "| - |"
                ),
                flush=True,
            )
        if args.out:  # after each size: a long run stopped later keeps what it measured
            write_json(report(args, rows), args.out)
    exponent = report(args, rows)["exponent"]
    if exponent is not None:
        print(f"\ntime ~ n^{exponent:.2f} (n: tetrahedra)")


def in_fresh_process(
    name: str, elements: int, linear_solver: str, steps, friction: float = FRICTION
) -> dict:
    """`run` in a fresh process: its peak resident memory is its own."""
    with ProcessPoolExecutor(max_workers=1, max_tasks_per_child=1) as pool:
        return pool.submit(run, name, elements, linear_solver, tuple(steps), friction).result()


def report(args: argparse.Namespace, rows: list[dict]) -> dict:
    """The machine, the command, the fitted exponent of time against tetrahedra (over the
    sizes that ran; None below two) and the rows."""
    done = [r for r in rows if "failed" not in r]
    exponent = None
    if len(done) >= 2:
        exponent = float(
            np.polyfit(
                np.log([r["tetrahedra"] for r in done]), np.log([r["seconds"] for r in done]), 1
            )[0]
        )
    command = "python benchmarks/fem_sizes.py " + " ".join(
        [
            f"--breast {args.breast}",
            "--elements",
            *map(str, args.elements),
            f"--linear-solver {args.linear_solver}",
            f"--steps {args.steps[0]} {args.steps[1]}",
            *([f"--against {args.against[0]} {args.against[1]}"] if args.against else []),
            *([f"--friction {args.friction}"] if args.friction != FRICTION else []),
        ]
    )
    return {
        "machine": platform.processor() or platform.machine(),
        "command": command,
        "exponent": exponent,
        "rows": rows,
    }


if __name__ == "__main__":
    main()
