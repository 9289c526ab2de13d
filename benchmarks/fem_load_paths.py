"""Uniqueness of the FE equilibrium: the same breast compressed along two load paths.

    python benchmarks/fem_load_paths.py --breasts P0001_L P0010_L P0153_L P0005_R P0120_R \
        --largest 10 --views cc mlo --workers 2 --out results/fem/load_paths.json

Each cohort breast (meshed from the cohort's generator and mesher settings,
``conf/generator/default.yaml``, ``conf/mesher/default.yaml``) goes through the unloaded state
(100 steps) and then the compression with the paper's settings (`fem.engine.simulation`:
friction 0.25, skin membrane, standing gravity, the sliding chest wall) to its target
compression ratio twice: in 70 and in 35 recorded steps (``--steps``). The final positions of
the two paths are compared (RMS and largest node distance, mm); the physical checks of the
70-step run are printed beside them (``--chest-wall``: the chest-wall mode, default sliding): the muscle's largest motion, the interface nodes' largest
motion along the chest-wall normal, the deepest skin node over a plate, the smallest element
volume ratio and the volume change. ``--largest N`` adds the N breasts of the cohort's
``--patients`` patients with the largest target compression ratio.
"""

from __future__ import annotations

import argparse
import platform
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np
from hydra.utils import instantiate
from omegaconf import OmegaConf

from fem import CONFIG_DIR
from fem.breasts.pool import one_blas_thread, worker_pool
from fem.contract.atomic import write_json
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue
from fem.engine.boundary import (
    chest_wall_nodes,
    chest_wall_normals,
    plate_schedule,
)
from fem.engine.simulation import compression, unloaded_state
from fem.engine.solver import SolverError


def cohort_breast(name: str):
    """The cohort's mesh of breast ``P<index>_<L|R>``."""
    generator = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "generator" / "default.yaml"))
    mesher = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "mesher" / "default.yaml"))
    volume, meta = generator.breast(int(name[1:5]), name[-1])
    return mesher(volume, meta)


def largest_compression(n_patients: int, count: int) -> list[str]:
    """The ``count`` breasts of the cohort's first ``n_patients`` with the largest target
    compression ratio (one per patient; both sides share it: the left one)."""
    generator = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "generator" / "default.yaml"))
    ratios = [generator.patient(i)["compression_ratio"] for i in range(n_patients)]
    return [f"P{i:04d}_L" for i in np.argsort(ratios)[::-1][:count]]


@one_blas_thread
def load_paths(name: str, view: str, steps: tuple[int, int], chest: str) -> dict:
    traj = cohort_breast(name)
    t0 = time.perf_counter()
    start = unloaded_state(traj, n_steps=100, chest=chest)[-1]
    unloaded_s = time.perf_counter() - t0
    ratio = traj.metadata["target_compression_ratio"]
    schedule = plate_schedule(traj, start, view=view, compression_ratio=ratio)
    finals, seconds = [], []
    for n in steps:
        t0 = time.perf_counter()
        result = compression(traj, start, schedule, n_steps=n, chest=chest)
        seconds.append(time.perf_counter() - t0)
        finals.append(result.positions[-1])
    x = finals[0]
    d = np.linalg.norm(finals[0] - finals[1], axis=1)
    wall = chest_wall_nodes(traj)
    muscle = np.setdiff1d(traj.cells[traj.tissue == Tissue.MUSCLE], wall)
    u = x - start
    skin = traj.flagged(NodeFlag.SKIN)
    depth = 0.0
    for origin, plate_normal, axis in result.plates[-1]:
        over = (x[skin] - origin) @ axis > 1e-9
        depth = max(depth, float(-((x[skin[over]] - origin) @ plate_normal).min(initial=0.0)))
    volume = signed_volume(x, traj.cells)
    return {
        "breast": name,
        "view": view,
        "chest_wall": chest,
        "volume_cm3": traj.metadata["breast_volume_cm3"],
        "compression_ratio": ratio,
        "elements": traj.n_cells,
        "rms_mm": float(np.sqrt((d**2).mean())),
        "max_mm": float(d.max()),
        "muscle_motion_mm": float(np.abs(u[muscle]).max(initial=0.0)),
        "interface_normal_motion_mm": float(
            np.abs(np.einsum("ij,ij->i", u[wall], chest_wall_normals(start[wall]))).max()
        ),
        "interface_slide_mm": float(np.linalg.norm(u[wall], axis=1).max()),
        "plate_penetration_mm": depth,
        "min_volume_ratio": float((volume / signed_volume(start, traj.cells)).min()),
        "volume_change": float(volume.sum() / signed_volume(start, traj.cells).sum() - 1),
        "unloaded_s": unloaded_s,
        "compression_s": seconds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--breasts", nargs="*", default=[])
    ap.add_argument("--largest", type=int, default=0)
    ap.add_argument("--patients", type=int, default=258)
    ap.add_argument("--views", nargs="+", default=["cc", "mlo"])
    ap.add_argument("--steps", nargs=2, type=int, default=[70, 35])
    ap.add_argument("--chest-wall", default="sliding", help="fem.engine.boundary.chest_wall mode")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    names = list(dict.fromkeys(args.breasts + largest_compression(args.patients, args.largest)))
    print(
        "| breast | view | volume (cm^3) | CR | RMS (mm) | max (mm) | muscle (mm) "
        "| along normal (mm) | slide (mm) | penetration (mm) | min vol. ratio | volume change "
        "| unloaded (s) | compression (s) |"
    )
    print("| --- " * 14 + "|")
    rows = []
    with worker_pool(args.workers) as pool:
        futures = [
            pool.submit(load_paths, n, v, tuple(args.steps), args.chest_wall)
            for n in names
            for v in args.views
        ]
        for future in as_completed(futures):
            try:
                r = future.result()
            except SolverError as exc:  # a breast that does not converge is a result too
                print(f"| failed: {exc} |", flush=True)
                rows.append({"failed": str(exc)})
                continue
            rows.append(r)
            print(
                f"| {r['breast']} | {r['view']} | {r['volume_cm3']:.0f} "
                f"| {r['compression_ratio']:.2f} | {r['rms_mm']:.3f} | {r['max_mm']:.3f} "
                f"| {r['muscle_motion_mm']:.1g} | {r['interface_normal_motion_mm']:.1g} "
                f"| {r['interface_slide_mm']:.1f} | {r['plate_penetration_mm']:.1g} "
                f"| {r['min_volume_ratio']:.2f} | {100 * r['volume_change']:+.2f} % "
                f"| {r['unloaded_s']:.1f} | {r['compression_s'][0]:.1f} |",
                flush=True,
            )
    if args.out:
        rows.sort(key=lambda r: (r.get("breast", ""), r.get("view", "")))
        write_json({"machine": platform.processor() or platform.machine(), "rows": rows}, args.out)


if __name__ == "__main__":
    main()
