"""Cohort command: virtual patients -> labelled volumes -> tetrahedral meshes, pictures, report.

    python -m fem.cohort                         # embedded default (conf/cohort.yaml)
    python -m fem.cohort n_patients=258 out_dir=data/cohort/full workers=2
    python -m fem.cohort ... simulate=false      # meshes only
    python -m fem.cohort ... executor=dask       # on Dask distributed (docs/distributed.md)
    python -m fem.cohort --config-name cohort_v2  # cohort v2: per-breast conditions, cc + mlo

Per breast ``P0007_L`` it writes ``P0007_L.vtu`` (ParaView, tissue fields), ``P0007_L.png``
(sections) and, last, ``P0007_L.npz`` (the `Trajectory`); a breast whose ``.npz`` exists is
finished and never redone, so a killed run resumes where it stopped. Every file is written
atomically. The cohort table (``cohort.csv``), report (``cohort.json``) and summary figure
(``cohort_summary.png``) are rebuilt from the finished breasts at the end of each run.

With ``simulate=true`` (the default) a second stage then simulates both FE steps on every
meshed breast (`fem.breasts.cohort_simulation`: ``<out_dir>/trajectories/``, equally resumable);
``refine=1`` simulates each on its mesh refined once (8x the elements) and records the
positions at the breast's own nodes (`fem.breasts.cohort_simulation.simulate_refined`).
``variation=v2`` (or ``--config-name cohort_v2``: the cohort v2, docs/cohort.md) simulates
each breast with its own drawn stiffness, friction and compressed thickness in each view of
the variation (`fem.breasts.conditions.ConditionSampler`; ``trajectories/`` for the first view,
``trajectories_<view>/`` for another).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from concurrent.futures import Executor, as_completed
from pathlib import Path

import hydra
import numpy as np
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from fem import CONFIG_DIR
from fem.breasts.cohort_simulation import simulate_cohort, trajectory_folder
from fem.breasts.conditions import ConditionSampler
from fem.breasts.figures import breast_sections_png, cohort_summary_png
from fem.breasts.io import write_mesh
from fem.breasts.mesh import Mesher
from fem.breasts.phantom import PhantomGenerator
from fem.breasts.pool import check_executor, check_workers, cohort_executor, one_blas_thread
from fem.contract.atomic import atomic_path, writable_folder
from fem.engine.simulation import Simulation

LATERALITIES = ("L", "R")


def breast_name(patient: int, laterality: str) -> str:
    return f"P{patient:04d}_{laterality}"


@one_blas_thread
def make_breast(
    generator: PhantomGenerator,
    mesher: Mesher,
    patient: int,
    laterality: str,
    out_dir: Path,
    figures: bool,
) -> dict:
    """Generate, mesh and write one breast; returns its metadata (with timings)."""
    t0 = time.perf_counter()
    volume, meta = generator.breast(patient, laterality)
    t1 = time.perf_counter()
    traj = mesher(volume, meta)
    t2 = time.perf_counter()
    name = breast_name(patient, laterality)
    write_mesh(traj, out_dir / f"{name}.vtu")
    if figures:
        breast_sections_png(traj, out_dir / f"{name}.png", volume)
    traj.metadata["timing_s"] = {
        "phantom": t1 - t0,
        "mesh": t2 - t1,
        "total": time.perf_counter() - t0,
    }
    traj.save(out_dir / f"{name}.npz")  # last: its presence marks the breast as finished
    return traj.metadata


def read_metadata(path: Path) -> dict:
    """Metadata of a finished breast, without loading its arrays."""
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["metadata"]))


def write_report(
    out_dir: Path, n_patients: int, failures: list[dict], wall_s: float | None
) -> dict:
    """Cohort table, report and summary figure from all finished breasts in ``out_dir``."""
    rows = [read_metadata(p) for p in sorted(out_dir.glob("P*_[LR].npz"))]
    rows = [r for r in rows if r["patient"] < n_patients]
    columns = [
        "patient",
        "laterality",
        "site",
        "age",
        "breast_volume_cm3",
        "glandular_fraction",
        "density_category",
        "uncompressed_thickness_mm",
        "target_compression_ratio",
        "compressed_thickness_mm",
    ]
    mesh_columns = ["n_elements", "n_nodes", "volume_error"]
    quality_columns = ["min_radius_ratio", "min_dihedral_deg", "max_dihedral_deg"]
    with atomic_path(out_dir / "cohort.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns + mesh_columns + quality_columns)
        for r in rows:
            writer.writerow(
                [r[c] for c in columns]
                + [r["mesh"][c] for c in mesh_columns]
                + [r["mesh"]["quality"][c] for c in quality_columns]
            )
    report: dict = {"n_patients": n_patients, "n_breasts_finished": len(rows), "failures": failures}
    if rows:
        n_el = [r["mesh"]["n_elements"] for r in rows]
        verr = [r["mesh"]["volume_error"] for r in rows]
        worst = min(rows, key=lambda r: r["mesh"]["quality"]["min_radius_ratio"])
        report.update(
            {
                "elements": {"min": min(n_el), "max": max(n_el), "median": float(np.median(n_el))},
                "volume_error": {
                    "min": min(verr),
                    "max": max(verr),
                    "max_abs": max(map(abs, verr)),
                },
                "worst_quality": {
                    "breast": breast_name(worst["patient"], worst["laterality"]),
                    **worst["mesh"]["quality"],
                },
                "surface_distance_mm": {
                    "max": max(r["mesh"]["surface_distance_mm"]["max"] for r in rows),
                    "median_p95": float(
                        np.median([r["mesh"]["surface_distance_mm"]["p95"] for r in rows])
                    ),
                },
                "min_dihedral_deg": min(r["mesh"]["quality"]["min_dihedral_deg"] for r in rows),
                "max_dihedral_deg": max(r["mesh"]["quality"]["max_dihedral_deg"] for r in rows),
                "n_inverted": sum(r["mesh"]["quality"]["n_inverted"] for r in rows),
                "sites": {
                    s: site_statistics([r for r in rows if r["site"] == s])
                    for s in sorted({r["site"] for r in rows})
                },
                "seconds_per_breast_cpu": float(np.mean([r["timing_s"]["total"] for r in rows])),
            }
        )
        cohort_summary_png(rows, out_dir / "cohort_summary.png")
    if wall_s is not None:
        report["wall_s_last_run"] = wall_s
    with atomic_path(out_dir / "cohort.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    if rows:
        with atomic_path(out_dir / "cohort_summary.md") as tmp:
            tmp.write_text(summary_markdown(report))
    return report


def summary_markdown(report: dict) -> str:
    """The cohort report as Markdown tables (per-site distributions, then meshes)."""
    sites = report["sites"]
    names = list(sites)

    def row(label: str, fmt) -> str:
        return f"| {label} | " + " | ".join(fmt(sites[s]) for s in names) + " |"

    def q(key: str, scale: float = 1.0, digits: int = 0) -> Callable[[dict], str]:
        return lambda st: (
            f"{scale * st[key]['median']:.{digits}f} ({scale * st[key]['p5']:.{digits}f}-"
            f"{scale * st[key]['p95']:.{digits}f}; {scale * st[key]['min']:.{digits}f}-{scale * st[key]['max']:.{digits}f})"
        )

    lines = [
        "| per site | " + " | ".join(f"site {s}" for s in names) + " |",
        "| --- | " + " | ".join("---" for _ in names) + " |",
        row("patients / breasts", lambda st: f"{st['patients']} / {st['breasts']}"),
        row("breast volume, cm^3: median (5-95 %; min-max)", q("breast_volume_cm3")),
        row("glandular fraction, %", q("glandular_fraction", 100, 1)),
        row(
            "BI-RADS a / b / c / d, %",
            lambda st: " / ".join(f"{100 * st['density_category_share'][c]:.0f}" for c in "abcd"),
        ),
        row("compression ratio, %", q("compression_ratio", 100)),
        row(
            "compression < 30 / 30-60 / > 60 %, % of breasts",
            lambda st: " / ".join(f"{100 * v:.0f}" for v in st["compression_ratio_share"].values()),
        ),
        row("compressed thickness, mm", q("compressed_thickness_mm")),
        "",
        "| meshes | value |",
        "| --- | --- |",
        f"| breasts meshed / failed | {report['n_breasts_finished']} / {len(report['failures'])} |",
        f"| tetrahedra per mesh: min / median / max | {report['elements']['min']} / "
        f"{report['elements']['median']:.0f} / {report['elements']['max']} |",
        f"| mesh vs segmented volume: min / max error | {100 * report['volume_error']['min']:+.2f} % / "
        f"{100 * report['volume_error']['max']:+.2f} % |",
        f"| inverted tetrahedra | {report['n_inverted']} |",
        f"| worst radius ratio (normalised, 1 = regular) | {report['worst_quality']['min_radius_ratio']:.3f} "
        f"({report['worst_quality']['breast']}) |",
        f"| dihedral angles over the cohort | {report['min_dihedral_deg']:.1f}-{report['max_dihedral_deg']:.1f} deg |",
        f"| surface nodes' distance from the segmented surface | median over breasts of the 95th percentile "
        f"{report['surface_distance_mm']['median_p95']:.2f} mm, max {report['surface_distance_mm']['max']:.1f} mm |",
        f"| CPU time per breast (phantom + mesh + files + PNG) | {report['seconds_per_breast_cpu']:.2f} s |",
    ]
    return "\n".join(lines) + "\n"


def site_statistics(rows: list[dict]) -> dict:
    """Breast count, quantiles of volume, glandular fraction and compression ratio, and
    density-category shares of one site."""

    def quantiles(values: list[float]) -> dict[str, float]:
        q = np.percentile(values, [0, 5, 50, 95, 100])
        return dict(zip(("min", "p5", "median", "p95", "max"), map(float, q), strict=True))

    cr = np.array([r["target_compression_ratio"] for r in rows])
    return {
        "breasts": len(rows),
        "patients": len({r["patient"] for r in rows}),
        "breast_volume_cm3": quantiles([r["breast_volume_cm3"] for r in rows]),
        "glandular_fraction": quantiles([r["glandular_fraction"] for r in rows]),
        "density_category_share": {
            c: float(np.mean([r["density_category"] == c for r in rows])) for c in "abcd"
        },
        "compression_ratio": quantiles(cr.tolist()),
        "compression_ratio_share": {
            "below_30": float(np.mean(cr < 0.3)),
            "30_to_60": float(np.mean((cr >= 0.3) & (cr <= 0.6))),
            "above_60": float(np.mean(cr > 0.6)),
        },
        "compressed_thickness_mm": quantiles([r["compressed_thickness_mm"] for r in rows]),
    }


def _flat(tree: object, prefix: str = "") -> dict[str, object]:
    """``{"a.b": value}`` of a nested mapping, without Hydra's ``_target_`` entries."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    out: dict[str, object] = {}
    for k, v in tree.items():
        if k != "_target_":
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def check_settings(out_dir: Path, cfg: DictConfig) -> None:
    """Refuse to resume a cohort made with other settings; record the settings otherwise.

    ``<out_dir>/cohort_config.json`` holds the generator's, the mesher's and (once simulated)
    the simulation's settings of the breasts in ``out_dir``, with the mesh refinement
    (``refine``) and the per-breast variation of the conditions (``variation``, null for the
    paper's cohort; a folder recorded before these settings existed resumes with 0 and null).
    ``n_patients`` may grow between runs (the cohort is extended); every other setting must
    match.

    Raises
    ------
    ValueError
        A stored setting differs from the requested one; the message names each key.
    """
    groups = ("generator", "mesher", "simulation") if cfg.simulate else ("generator", "mesher")
    requested = {g: OmegaConf.to_container(cfg[g], resolve=True) for g in groups}
    path = out_dir / "cohort_config.json"
    stored = json.loads(path.read_text()) if path.exists() else {}
    if cfg.simulate:  # mesh refinement, per-breast variation (folders made before: 0, null)
        groups += ("refine", "variation")
        requested["refine"] = cfg.refine
        variation = cfg.get("variation")
        requested["variation"] = (
            None if variation is None else OmegaConf.to_container(variation, resolve=True)
        )
        if stored:
            stored.setdefault("refine", 0)
            stored.setdefault("variation", None)
    old, new = _flat({g: stored[g] for g in groups if g in stored}), _flat(requested)
    new = {k: v for k, v in new.items() if k.split(".")[0] in stored}
    differ = sorted(set(old) ^ set(new) | {k for k in set(old) & set(new) if old[k] != new[k]})
    if differ:
        raise ValueError(
            f"{path}: the breasts in {out_dir} were made with other settings: "
            + "; ".join(
                f"{k}: {old.get(k, '(none)')} there, {new.get(k, '(none)')} now" for k in differ
            )
            + ". Use another out_dir, or delete this one to rebuild it."
        )
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**stored, **requested}, indent=2))


def mesh_cohort(
    pool: Executor,
    generator: PhantomGenerator,
    mesher: Mesher,
    out_dir: Path,
    n_patients: int,
    figures: bool,
) -> list[dict]:
    """Generate and mesh every unfinished breast of the cohort on ``pool``; returns the failures.

    A breast whose ``.npz`` exists in ``out_dir`` is finished and skipped; a failed breast is
    reported (name and reason), never written.
    """
    todo = [
        (p, lat)
        for p in range(n_patients)
        for lat in LATERALITIES
        if not (out_dir / f"{breast_name(p, lat)}.npz").exists()
    ]
    failures: list[dict] = []
    with tqdm(
        total=2 * n_patients,
        initial=2 * n_patients - len(todo),
        unit="breast",
        desc=f"cohort -> {out_dir}",
    ) as bar:
        futures = {
            pool.submit(make_breast, generator, mesher, p, lat, out_dir, figures): (p, lat)
            for p, lat in todo
        }
        for fut in as_completed(futures):
            p, lat = futures[fut]
            try:
                fut.result()
            except Exception as exc:  # a failed breast is reported, never written
                failures.append(
                    {"breast": breast_name(p, lat), "reason": f"{type(exc).__name__}: {exc}"}
                )
                tqdm.write(f"FAILED {breast_name(p, lat)}: {exc}")
            bar.update()
    return failures


def run_cohort(cfg: DictConfig) -> dict:
    """Generate every unfinished breast of the cohort in parallel, then write the report.

    Every setting is checked before anything is written: ``n_patients`` and ``workers``, the
    executor (``executor``, ``scheduler``: `fem.breasts.pool.check_executor`), the output
    folder, the generator, mesher, simulation and variation (``variation``: per-breast
    conditions, `fem.breasts.conditions.ConditionSampler`, null for the paper's cohort) built
    from ``cfg`` and compared with the settings the folder's breasts were made with
    (`check_settings`). Both stages run their per-breast tasks on one executor
    (`fem.breasts.pool.cohort_executor`): the local process pool or Dask distributed, with the
    same files.

    Raises
    ------
    ValueError
        A setting out of range, or other settings than those of the folder's breasts; the
        message names the setting.
    PermissionError
        ``out_dir`` cannot be written.
    """
    if not (isinstance(cfg.n_patients, int) and cfg.n_patients >= 1):
        raise ValueError(f"n_patients must be an integer >= 1, got {cfg.n_patients!r}")
    check_workers(cfg.workers)
    if not (isinstance(cfg.refine, int) and cfg.refine >= 0):
        raise ValueError(f"refine must be an integer >= 0, got {cfg.refine!r}")
    check_executor(cfg.executor, cfg.scheduler)
    out_dir = writable_folder(to_absolute_path(cfg.out_dir))
    generator: PhantomGenerator = instantiate(cfg.generator)
    mesher: Mesher = instantiate(cfg.mesher)
    simulation: Simulation | None = instantiate(cfg.simulation) if cfg.simulate else None
    variation: ConditionSampler | None = None
    if simulation is not None and cfg.get("variation") is not None:
        variation = instantiate(cfg.variation)
        variation.check(simulation)
    out_dir.mkdir(parents=True, exist_ok=True)
    check_settings(out_dir, cfg)
    with cohort_executor(cfg.executor, cfg.workers, cfg.scheduler) as pool:
        t0 = time.perf_counter()
        failures = mesh_cohort(pool, generator, mesher, out_dir, cfg.n_patients, cfg.figures)
        report = write_report(out_dir, cfg.n_patients, failures, time.perf_counter() - t0)
        print(json.dumps({k: v for k, v in report.items() if k != "failures"}, indent=2))
        print(f"{len(failures)} failures; outputs in {out_dir}")
        if simulation is not None:
            names = [breast_name(p, lat) for p in range(cfg.n_patients) for lat in LATERALITIES]
            report["simulation"] = simulate_cohort(
                pool,
                out_dir,
                names,
                simulation,
                cfg.time_series,
                cfg.retry_failed,
                cfg.refine,
                variation,
            )
            views = (None,) if variation is None else variation.views
            for i, view in enumerate(views):
                folder = trajectory_folder(out_dir, i, view)
                print(
                    (f"{folder}:\n" if i else "") + (folder / "simulation_summary.md").read_text()
                )
    return report


@hydra.main(config_path=CONFIG_DIR, config_name="cohort", version_base="1.3")
def main(cfg: DictConfig) -> None:
    report = run_cohort(cfg)
    if report["failures"]:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
