"""Mesh convergence of the FE ground truth on cohort breasts.

    python benchmarks/fem_convergence_breasts.py --breasts P0001_L P0010_L ... \
        --factors 1 2 4 --workers 2 --out results/fem/convergence_breasts.json

Each breast's segmentation (the cohort's generator, ``conf/generator/default.yaml``) is meshed
at the cohort resolution (``conf/mesher/default.yaml``: about 2,250 tetrahedra) and at
``--factors`` times as many elements; each mesh goes through both steps with the paper's
settings (`fem.engine.simulation`: 100 unloaded-state steps, 70 compression steps to the
breast's target compression ratio, friction 0.25, skin membrane, cc view) and the chest wall
``--chest-wall`` (default sliding).
The unloaded shape and the final compressed shape of every finer mesh are interpolated
(linear, in the imaged configuration) at the imaged positions of the cohort mesh's nodes
(`fem.contract.quality`-free: scikit-fem's element finder; a node outside the finer mesh takes
the values of its nearest node) and compared with the cohort mesh's own: RMS and 95th
percentile of the node distance, mm, against the finest mesh, and the smallest volume ratio
of the cohort mesh's elements under the finest answer at its nodes (below 0: sampled at the
cohort nodes, the finer answer inverts a cohort element).

``--nested`` refines the cohort mesh itself instead (`fem.breasts.mesh.refine`: every tetrahedron split into
eight per level, factors 1, 8, 64), so all meshes have the same geometry, tissue boundaries
and held chest wall and the differences are discretisation error only. A refined run is the
cohort's refined ground truth (`fem.breasts.cohort_simulation.simulate_refined`): recorded at
the cohort nodes and projected onto valid cohort shapes; its rows carry how far the projection
moved the nodes (RMS and maximum over the steps, mm), and the volume-ratio column is of the
answer before the projection.
"""

from __future__ import annotations

import argparse
import platform
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np
import skfem
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

from fem import CONFIG_DIR
from fem.breasts.cohort_simulation import simulate_refined
from fem.breasts.pool import one_blas_thread, worker_pool
from fem.contract.atomic import write_json
from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from fem.engine.simulation import Simulation, SimulationFailed


def sample(fine: Trajectory, fields: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Linear interpolation of nodal ``fields`` (K, Nf, 3) of ``fine`` at imaged ``points``
    (N, 3); points outside the mesh take their nearest fine node's values. (K, N, 3)."""
    mesh = skfem.MeshTet(fine.points.T.copy(), fine.cells.T.copy())
    finder = mesh.element_finder()
    out = np.empty((len(fields), len(points), 3))
    inside = np.zeros(len(points), bool)
    try:
        cells = finder(*points.T)
        inside = cells >= 0
    except ValueError:  # some point outside every element: locate one by one
        cells = np.full(len(points), -1)
        for i, p in enumerate(points):
            try:
                cells[i] = finder(*p[:, None])[0]
            except ValueError:
                continue
        inside = cells >= 0
    if inside.any():
        c = fine.cells[cells[inside]]
        v = fine.points[c]  # (M, 4, 3)
        T = np.swapaxes(v[:, 1:] - v[:, :1], 1, 2)
        lam = np.linalg.solve(T, (points[inside] - v[:, 0])[..., None])[..., 0]
        weights = np.concatenate([1 - lam.sum(1, keepdims=True), lam], axis=1)  # (M, 4)
        out[:, inside] = np.einsum("mk,tmkd->tmd", weights, fields[:, c])
    if (~inside).any():
        nearest = cKDTree(fine.points).query(points[~inside])[1]
        out[:, ~inside] = fields[:, nearest]
    return out


@one_blas_thread
def simulate(
    name: str, factor: float, chest: str, nested: bool
) -> tuple[str, float, Trajectory, float]:
    generator = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "generator" / "default.yaml"))
    mesher_cfg = OmegaConf.load(Path(CONFIG_DIR) / "mesher" / "default.yaml")
    if not nested:
        mesher_cfg.target_elements = int(mesher_cfg.target_elements * factor)
        mesher_cfg.tolerance = int(mesher_cfg.tolerance * factor)
    volume, meta = generator.breast(int(name[1:5]), name[-1])
    traj = instantiate(mesher_cfg)(volume, meta)
    levels = round(np.log(factor) / np.log(8)) if nested else 0
    t0 = time.perf_counter()
    result = simulate_refined(Simulation(chest_wall=chest), traj, levels)
    return name, factor, result, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--breasts", nargs="+", required=True)
    ap.add_argument("--factors", nargs="+", type=float, default=[1.0, 2.0, 4.0])
    ap.add_argument("--chest-wall", default="sliding", help="fem.engine.boundary.chest_wall mode")
    ap.add_argument(
        "--nested",
        action="store_true",
        help="refine the cohort mesh itself (factors must be powers of 8) instead of remeshing",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    runs: dict[tuple[str, float], tuple[Trajectory, float]] = {}
    rows: list[dict] = []
    print(
        "| breast | volume (cm^3) | CR | tetrahedra | unloaded RMS / p95 (mm) "
        "| compressed RMS / p95 (mm) | finest answer's smallest cohort-element volume ratio "
        "| time (s) |"
    )
    print("| --- " * 8 + "|", flush=True)
    with worker_pool(args.workers) as pool:
        futures = [
            pool.submit(simulate, n, f, args.chest_wall, args.nested)
            for n in args.breasts
            for f in sorted(args.factors)[::-1]
        ]
        for future in as_completed(futures):
            try:
                name, factor, traj, seconds = future.result()
            except SimulationFailed as exc:  # the breast is left out of the table
                print(f"failed: {exc}", flush=True)
                continue
            runs[name, factor] = traj, seconds
            if all((name, f) in runs for f in args.factors):  # a breast's rows, as they come
                rows += compare(name, runs, args)
                if args.out:
                    machine = platform.processor() or platform.machine()
                    write_json({"machine": machine, "rows": rows}, args.out)


def compare(
    name: str, runs: dict[tuple[str, float], tuple[Trajectory, float]], args: argparse.Namespace
) -> list[dict]:
    """The rows of breast ``name`` (all its ``args.factors`` in ``runs``), printed."""
    rows = []
    coarse, _ = runs[name, min(args.factors)]
    reference = runs[name, max(args.factors)][0]
    ref = sample(
        reference, np.stack([reference.unloaded[-1], reference.compressed[-1]]), coarse.points
    )
    # the finest answer at the coarse nodes: does it invert a coarse element (before the
    # projection of a nested answer, which then moved it by ``projection``)?
    ratio = signed_volume(ref[1], coarse.cells) / signed_volume(coarse.points, coarse.cells)
    projection = reference.metadata["simulation"].get("projection")
    if projection is not None:
        ratio = np.array([projection["min_element_volume_ratio_before"]])
    for factor in sorted(args.factors):
        traj, seconds = runs[name, factor]
        own = sample(traj, np.stack([traj.unloaded[-1], traj.compressed[-1]]), coarse.points)
        d = np.linalg.norm(own - ref, axis=2)  # (2, N)
        row = {
            "breast": name,
            "chest_wall": args.chest_wall,
            "nested": args.nested,
            "factor": factor,
            "tetrahedra": traj.metadata["simulation"].get("refined_tetrahedra", traj.n_cells),
            "volume_cm3": traj.metadata["breast_volume_cm3"],
            "compression_ratio": traj.metadata["target_compression_ratio"],
            "unloaded_rms_mm": float(np.sqrt((d[0] ** 2).mean())),
            "unloaded_p95_mm": float(np.percentile(d[0], 95)),
            "compressed_rms_mm": float(np.sqrt((d[1] ** 2).mean())),
            "compressed_p95_mm": float(np.percentile(d[1], 95)),
            "reference_min_volume_ratio": float(ratio.min()),
            "seconds": seconds,
        }
        if projection is not None:
            row["projection_moved_rms_mm"] = projection["moved_rms_mm"]
            row["projection_moved_max_mm"] = projection["moved_max_mm"]
        rows.append(row)
        print(
            f"| {name} | {row['volume_cm3']:.0f} | {row['compression_ratio']:.2f} "
            f"| {row['tetrahedra']} | {row['unloaded_rms_mm']:.2f} / {row['unloaded_p95_mm']:.2f} "
            f"| {row['compressed_rms_mm']:.2f} / {row['compressed_p95_mm']:.2f} "
            f"| {row['reference_min_volume_ratio']:.2f} | {seconds:.0f} |",
            flush=True,
        )
    return rows


if __name__ == "__main__":
    main()
