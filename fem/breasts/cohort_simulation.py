"""The cohort command's simulation stage: both FE steps on every meshed breast, and its report.

    python -m fem.cohort n_patients=258 out_dir=data/cohort/full simulate=true workers=2
    python -m fem.cohort ... executor=dask [scheduler=tcp://host:8786]  # on Dask distributed

For each mesh ``<out_dir>/P0007_L.npz`` the stage writes ``<out_dir>/trajectories/P0007_L.npz``
(the `Trajectory` with both steps, the training data of ``datamodules/``) or, when a step does
not converge, ``P0007_L.failed.json`` with the step and the reason; a failed breast is never
written as a result. Bad settings or input (a `ValueError`) are no failure of the breast: they
end the command, and nothing is stored for the breast. Either file marks the breast as done, so a killed run resumes where it
stopped (``retry_failed=true`` tries the failures again). Every file is written atomically.
The report (``simulation.csv``, ``simulation.json``, ``simulation_summary.md`` and
``simulation_summary.png``) is rebuilt from all finished breasts at the end of each run.

With a ``variation`` (`fem.breasts.conditions.ConditionSampler`, the cohort v2) every breast
is simulated with its own drawn conditions (``dataclasses.replace(simulation, ...)``: materials,
friction, view, angle, compression ratio) once per view of the variation: the first view's
trajectories go to ``<out_dir>/trajectories/``, any other view's to
``<out_dir>/trajectories_<view>/`` (``trajectories_mlo/``), each folder with the same file
names (``P0007_L.npz``) and its own report. The trajectory's ``metadata["simulation"]`` records
the conditions used, ``metadata["variation"]`` the draw (seed, view, factor, target ratio).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Sequence
from concurrent.futures import Executor, as_completed
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fem.breasts.conditions import ConditionSampler
from fem.breasts.figures import simulation_summary_png
from fem.breasts.mesh import refine
from fem.breasts.pool import one_blas_thread
from fem.contract.atomic import atomic_path
from fem.contract.projection import StepProjections, constraints, project_steps
from fem.contract.quality import signed_volume
from fem.contract.timeseries import write_time_series
from fem.contract.trajectory import NodeFlag, Trajectory
from fem.engine.boundary import chest_wall, read_constraints
from fem.engine.constraints import HeldDirections
from fem.engine.simulation import Simulation, SimulationFailed, shape_changes

#: Smallest element volume ratio (to the step's start) of a refined ground truth at the coarse
#: nodes (`simulate_refined`): below every cc cohort breast's own FE answer (to the imaged
#: mesh: 0.039 at least, 0.39 the median), so the projection moves only what a coarse element
#: cannot be.
REFINED_MIN_VOLUME_RATIO = 0.03

COLUMNS = (
    "name",
    "status",
    "step",
    "reason",
    "volume_cm3",
    "n_elements",
    "target_compression_ratio",
    "compression_ratio",
    "compressed_thickness_mm",
    "volume_change",
    "max_unloaded_displacement_mm",
    "time_unloaded_s",
    "time_compression_s",
)


def simulate_refined(simulation: Simulation, traj: Trajectory, levels: int) -> Trajectory:
    """Both steps of ``simulation`` on ``traj``'s mesh refined ``levels`` times
    (`fem.breasts.mesh.refine`: 8^levels the elements, same geometry), returned at ``traj``'s
    own nodes: a ground truth closer to the converged answer on the mesh the models see.
    ``levels=0`` simulates ``traj`` itself.

    Sampled at the coarse nodes, the fine answer can invert coarse elements (the fine mesh
    folds where a coarse element cannot, docs/fem-convergence.md), so every recorded shape is
    projected onto valid coarse shapes (`fem.contract.projection.project_steps`: each
    element's volume ratio to the step's start at least `REFINED_MIN_VOLUME_RATIO`, no skin
    node inside a plate, the chest wall held as the step holds it). The metadata's
    checks are of the coarse mesh's elements after the projection; ``simulation`` also says
    what ran (``refine_levels``, ``refined_tetrahedra``) and what the projection did
    (``projection``: the smallest volume ratio before it, steps it moved, the largest RMS and
    maximum node displacement over the steps, mm).

    Raises
    ------
    ValueError
        Element sets (``simulation.materials.<name>.elements``) with ``levels > 0``: their
        element numbers are the coarse mesh's.
    SimulationFailed
        A step did not converge, or (step ``projection``) no valid coarse shape was found.
    """
    if levels == 0:
        return simulation(traj)
    sets = [name for name, m in simulation.materials.items() if m.elements is not None]
    if sets:
        raise ValueError(
            f"simulation.materials.{sets[0]}.elements: element sets number the paper-resolution "
            f"mesh's elements; refine={levels} cannot use them (set refine=0)"
        )
    fine, _ = refine(traj, levels)
    result = simulation(fine)
    n = traj.n_nodes
    unloaded, compressed = result.unloaded[:, :n], result.compressed[:, :n]
    before = signed_volume(compressed[-1], traj.cells) / signed_volume(traj.points, traj.cells)
    skin = traj.flagged(NodeFlag.SKIN)

    user = (
        read_constraints(simulation.constraints, traj.n_nodes)
        if simulation.constraints is not None
        else HeldDirections.none()
    )

    def valid(steps: np.ndarray, start: np.ndarray, plates=None) -> StepProjections:
        held = chest_wall(traj, start, simulation.chest_wall) + user  # as the step holds it
        c = constraints(
            traj.cells,
            start,
            None if plates is None else skin,
            REFINED_MIN_VOLUME_RATIO,
            held=(held.nodes, held.directions),
        )
        p = project_steps(c, steps, plates)
        if p.failed:  # the breast fails, the cohort goes on
            step, why = next(iter(p.failed.items()))
            seconds = result.metadata["simulation"]["seconds"]
            raise SimulationFailed(traj.source, "projection", f"step {step + 1}: {why}", seconds)
        return p

    projections = [valid(unloaded, traj.points)]
    start = projections[0].points[-1] if len(unloaded) else traj.points
    projections.append(valid(compressed, start, result.plates))
    unloaded, compressed = (p.points for p in projections)
    start = unloaded[-1] if len(unloaded) else traj.points
    checks = shape_changes(traj.points, traj.cells, start, compressed[-1])
    metadata = dict(result.metadata)
    metadata["simulation"] = {
        **metadata["simulation"],
        **checks,
        "refine_levels": levels,
        "refined_tetrahedra": fine.n_cells,
        "projection": {
            "min_volume_ratio": REFINED_MIN_VOLUME_RATIO,
            "min_element_volume_ratio_before": float(before.min()),
            "steps_moved": int(sum((p.sweeps > 0).sum() for p in projections)),
            "moved_rms_mm": float(max(p.moved_rms_mm.max(initial=0.0) for p in projections)),
            "moved_max_mm": float(max(p.moved_max_mm.max(initial=0.0) for p in projections)),
        },
    }
    return replace(
        traj,
        unloaded=unloaded,
        compressed=compressed,
        plates=result.plates,
        compression_ratio=result.compression_ratio,
        metadata=metadata,
    )


def trajectory_folder(mesh_dir: Path, view_index: int = 0, view: str | None = None) -> Path:
    """Where the cohort's simulated breasts of a view go: ``<mesh_dir>/trajectories`` for the
    first (or only) view, ``<mesh_dir>/trajectories_<view>`` for any other view of a
    variation."""
    return mesh_dir / ("trajectories" if view_index == 0 else f"trajectories_{view}")


def varied(
    simulation: Simulation,
    variation: ConditionSampler,
    traj: Trajectory,
    name: str,
    view: str | None = None,
) -> tuple[Simulation, Trajectory]:
    """``simulation`` with breast ``name``'s drawn conditions in ``view``
    (`ConditionSampler.sample` around the breast's target ratio), and ``traj`` with the draw
    in its metadata (``variation``: seed, view, compression-ratio factor, target ratio).

    Raises
    ------
    ValueError
        No target compression ratio (`Simulation.target_ratio`), or a view not sampled.
    """
    draw = variation.sample(name, simulation.target_ratio(traj), view)
    record = {
        "seed": variation.seed,
        "view": draw["view"],
        "compression_ratio_factor": draw["compression_ratio_factor"],
        "target_compression_ratio": draw["compression_ratio"],
    }
    traj = replace(traj, metadata={**traj.metadata, "variation": record})
    return replace(simulation, **variation.overrides(simulation, draw)), traj


@one_blas_thread
def simulate_breast(
    simulation: Simulation,
    mesh: Path,
    out_dir: Path,
    time_series: bool = False,
    refine_levels: int = 0,
    variation: ConditionSampler | None = None,
    view: str | None = None,
) -> dict:
    """Simulate one meshed breast (on its mesh refined ``refine_levels`` times:
    `simulate_refined`; with a ``variation``, with its drawn conditions in ``view``: `varied`)
    and write its result or its failure; returns its report row."""
    traj = Trajectory.load(mesh)
    traj.metadata.setdefault("source", str(mesh))
    row = {
        "name": mesh.stem,
        "volume_cm3": traj.metadata.get("breast_volume_cm3", float("nan")),
        "n_elements": traj.n_cells,
        "target_compression_ratio": traj.metadata.get("target_compression_ratio", float("nan")),
    }
    if variation is not None:
        simulation, traj = varied(simulation, variation, traj, mesh.stem, view)
    try:
        row["target_compression_ratio"] = simulation.target_ratio(traj)
        result = simulate_refined(simulation, traj, refine_levels)
    except SimulationFailed as exc:  # a settings or input error (ValueError) ends the command
        row.update(
            status="failed",
            step=exc.step,
            reason=exc.reason,
            time_unloaded_s=exc.seconds.get("unloaded", float("nan")),
            time_compression_s=exc.seconds.get("compression", float("nan")),
        )
        with atomic_path(out_dir / f"{mesh.stem}.failed.json") as tmp:
            tmp.write_text(json.dumps(row, indent=2))
        return row
    if time_series:
        write_time_series(result, out_dir / f"{mesh.stem}.xdmf")
    result.save(out_dir / f"{mesh.stem}.npz")
    return {**row, **result_row(result.metadata)}


def result_row(metadata: dict) -> dict:
    """The report columns of a simulated breast from its metadata."""
    sim = metadata["simulation"]
    return {
        "status": "ok",
        "step": "",
        "reason": "",
        "compression_ratio": sim["compression_ratio"],
        "compressed_thickness_mm": sim["compressed_thickness_mm"],
        "volume_change": sim["volume_change"],
        "max_unloaded_displacement_mm": sim["max_unloaded_displacement_mm"],
        "time_unloaded_s": sim["seconds"].get("unloaded", 0.0),
        "time_compression_s": sim["seconds"]["compression"],
    }


def finished_rows(out_dir: Path, names: Sequence[str]) -> list[dict]:
    """Report rows of the finished breasts among ``names`` (results and failures)."""
    rows = []
    for name in names:
        failed = out_dir / f"{name}.failed.json"
        result = out_dir / f"{name}.npz"
        if result.exists():
            with np.load(result, allow_pickle=False) as z:
                meta = json.loads(str(z["metadata"]))
                n_elements = len(z["cells"])
            target = meta.get("variation", {}).get(
                "target_compression_ratio", meta.get("target_compression_ratio")
            )  # a variation's jittered target, else the breast's own
            rows.append(
                {
                    "name": name,
                    "volume_cm3": meta.get("breast_volume_cm3", float("nan")),
                    "n_elements": n_elements,
                    "target_compression_ratio": target,
                    **result_row(meta),
                }
            )
        elif failed.exists():
            rows.append({**dict.fromkeys(COLUMNS, float("nan")), **json.loads(failed.read_text())})
    return rows


def write_simulation_report(out_dir: Path, names: Sequence[str], wall_s: float | None) -> dict:
    """``simulation.csv``/``.json``/``_summary.md``/``_summary.png`` from the finished breasts."""
    rows = finished_rows(out_dir, names)
    with atomic_path(out_dir / "simulation.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    ok = [r for r in rows if r["status"] == "ok"]
    failed = [r for r in rows if r["status"] != "ok"]

    def stats(values: Sequence[float]) -> dict[str, float]:
        v = np.asarray(values, float)
        if not len(v):
            return {}
        q = np.percentile(v, [0, 50, 95, 100])
        return dict(zip(("min", "median", "p95", "max"), map(float, q), strict=True))

    report = {
        "n_breasts": len(names),
        "n_finished": len(rows),
        "n_converged": len(ok),
        "n_failed": len(failed),
        "converged_share": len(ok) / len(rows) if rows else float("nan"),
        "reached_target": sum(
            abs(r["compression_ratio"] - r["target_compression_ratio"]) < 1e-6 for r in ok
        ),
        "compression_ratio": stats([r["compression_ratio"] for r in ok]),
        "volume_change": stats([r["volume_change"] for r in ok]),
        "seconds_unloaded": stats([r["time_unloaded_s"] for r in ok]),
        "seconds_compression": stats([r["time_compression_s"] for r in ok]),
        "seconds_total": stats([r["time_unloaded_s"] + r["time_compression_s"] for r in ok]),
        "failures": [{k: r[k] for k in ("name", "step", "reason")} for r in failed],
    }
    if wall_s is not None:
        report["wall_s_last_run"] = wall_s
    with atomic_path(out_dir / "simulation.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    with atomic_path(out_dir / "simulation_summary.md") as tmp:
        tmp.write_text(simulation_markdown(report))
    if rows:
        simulation_summary_png(rows, out_dir / "simulation_summary.png")
    return report


def simulation_markdown(report: dict) -> str:
    """The simulation report as a Markdown table, then the failures."""

    def q(key: str, fmt: str = ".1f", scale: float = 1.0) -> str:
        s = report[key]
        if not s:
            return "-"
        return (
            f"{scale * s['median']:{fmt}} (min {scale * s['min']:{fmt}}, 95 % "
            f"{scale * s['p95']:{fmt}}, max {scale * s['max']:{fmt}})"
        )

    lines = [
        "| simulation | value |",
        "| --- | --- |",
        f"| breasts finished / in cohort | {report['n_finished']} / {report['n_breasts']} |",
        f"| converged (both steps, target thickness reached) | {report['n_converged']} "
        f"({100 * report['converged_share']:.1f} %) |",
        f"| failed | {report['n_failed']} |",
        f"| final compression ratio, %: median | {q('compression_ratio', '.0f', 100)} |",
        f"| volume change at the last step, % | {q('volume_change', '.2f', 100)} |",
        f"| time, unloaded state (s) | {q('seconds_unloaded')} |",
        f"| time, compression (s) | {q('seconds_compression')} |",
        f"| time per breast, both steps (s) | {q('seconds_total')} |",
    ]
    if report["failures"]:
        lines += ["", "| failed breast | step | reason |", "| --- | --- | --- |"]
        lines += [f"| {f['name']} | {f['step']} | {f['reason']} |" for f in report["failures"]]
    return "\n".join(lines) + "\n"


def simulate_cohort(
    pool: Executor,
    mesh_dir: Path,
    names: Sequence[str],
    simulation: Simulation,
    time_series: bool = False,
    retry_failed: bool = False,
    refine_levels: int = 0,
    variation: ConditionSampler | None = None,
) -> dict:
    """Simulate every unfinished breast of ``names`` (meshes in ``mesh_dir``) on ``pool``, on
    its mesh refined ``refine_levels`` times (`simulate_refined`); with a ``variation``, each
    with its own drawn conditions, once per view of the variation (`varied`).

    Results go to ``mesh_dir / "trajectories"`` (a variation's other views: to
    ``trajectories_<view>``, `trajectory_folder`); a breast whose result or failure file is
    in its folder is finished and skipped. Returns the report of the first folder; with
    several views, ``by_view`` holds every view's report.

    Raises
    ------
    ValueError
        A variation that cannot apply to ``simulation`` (`ConditionSampler.check`), or bad
        settings or input met while simulating.
    """
    if variation is not None:
        variation.check(simulation)
    views: tuple[str | None, ...] = (None,) if variation is None else tuple(variation.views)
    folders = {view: trajectory_folder(mesh_dir, i, view) for i, view in enumerate(views)}
    for out_dir in folders.values():
        out_dir.mkdir(parents=True, exist_ok=True)
        if retry_failed:
            for name in names:
                (out_dir / f"{name}.failed.json").unlink(missing_ok=True)
    todo = [
        (n, view)
        for view, out_dir in folders.items()
        for n in names
        if (mesh_dir / f"{n}.npz").exists()
        and not (out_dir / f"{n}.npz").exists()
        and not (out_dir / f"{n}.failed.json").exists()
    ]
    total = len(names) * len(views)
    t0 = time.perf_counter()
    with tqdm(
        total=total,
        initial=total - len(todo),
        unit="breast",
        desc=f"simulate -> {folders[views[0]]}"
        + (f" (+{len(views) - 1} views)" if len(views) > 1 else ""),
    ) as bar:
        futures = {
            pool.submit(
                simulate_breast,
                simulation,
                mesh_dir / f"{n}.npz",
                folders[view],
                time_series,
                refine_levels,
                variation,
                view,
            ): n
            for n, view in todo
        }
        for fut in as_completed(futures):
            row = fut.result()
            if row["status"] != "ok":
                tqdm.write(f"FAILED {row['name']} ({row['step']}): {row['reason']}")
            bar.update()
    wall_s = time.perf_counter() - t0
    reports = {view: write_simulation_report(d, names, wall_s) for view, d in folders.items()}
    report = reports[views[0]]
    if len(views) > 1:
        report = {**report, "by_view": reports}
    return report
