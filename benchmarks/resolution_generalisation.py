"""Does the graph surrogate generalise across mesh resolutions? The validation breasts of a
run's split (fold 0 of the 10-fold cross-validation by default: 52 breasts) are remeshed from
their segmentations at ``--factors`` times the cohort's element count (2x and 4x: about 4,500
and 9,000 tetrahedra instead of 2,250) and simulated there with the cohort's own settings; the
models (by default the committed graph models of the split's fold, `results/cv/mesh_gnn`;
a model trained on another split is refused, as its training breasts could be among these)
then predict each breast at every resolution and are compared with the FE on the same mesh.

    python benchmarks/resolution_generalisation.py --limit 2            # a quick check
    nohup python benchmarks/resolution_generalisation.py --factors 2 4 \
        --out results/resolution/mesh_gnn_fold0.json > resolution.log 2>&1 &
    python benchmarks/resolution_generalisation.py --no-simulate        # evaluate what is done
    python benchmarks/resolution_generalisation.py --limit 26 --train-breasts 30 --workers 2 \
        --no-evaluate     # also 30 training breasts at 2x and 4x, for data.augment_dir
    python benchmarks/resolution_generalisation.py \
        --unloaded outputs/.../unloaded/checkpoints/best.ckpt \
        --compression outputs/.../compression/checkpoints/best.ckpt   # another model
    python benchmarks/resolution_generalisation.py --pool results/resolution/fold[0-9]_finetuned_multires.json \
        --out results/resolution/pooled_finetuned.json     # several folds' breasts, one table

Breasts, meshes and FE: the cohort's generator, mesher and simulation are built from
``<cohort>/cohort_config.json`` (the settings the cohort was made with), the mesher with
``target_elements`` and ``tolerance`` times the factor. Each breast is meshed by the cohort's
own `fem.cohort.make_breast` into ``<out-root>/<factor>x/<name>.npz`` and simulated by
`fem.breasts.cohort_simulation.simulate_breast` into ``<out-root>/<factor>x/trajectories/``
(``<name>.npz``, or ``<name>.failed.json`` when a step does not converge), both written
atomically and skipped when present, so a killed run resumes; ``<out-root>/<factor>x/
cohort_config.json`` records the settings and a folder made with others is refused
(`fem.cohort.check_settings`). Breasts are done one after the other, every factor of a breast
before the next breast, so a run stopped early still leaves breasts finished at every
resolution; ``--workers`` processes (`fem.breasts.pool.worker_pool`, one BLAS thread each as in
the cohort) take the (breast, factor) tasks in that order. A breast whose meshing or FE fails
is reported (name, factor, reason) and skipped.

Training at several resolutions: ``--train-breasts N`` also remeshes and simulates N training
breasts of the same split (evenly spaced in its sorted list) into the same folders; a model
trained with ``data.augment_dir=[<out-root>/2x/trajectories,<out-root>/4x/trajectories]``
learns from those of its training patients only (`datamodules.trajectories`: the validation
breasts in these folders are never trained on) and is then evaluated here like any other.
The native row is the cohort's own trajectories (``<cohort>/trajectories/``).

Evaluation, on the breasts finished at every resolution only (paired): the two steps are
judged separately, as the report does. The unloaded-state model predicts from the imaged mesh
and is compared with the FE unloaded state; the compression model starts from the FE unloaded
state at the FE's compressed thickness and is compared with the FE compression
(`mammo_net.metrics.breast_rmse`: mean node RMSE over all recorded steps and at the last one,
mm). The table gives the mean over breasts with its ratio to the native resolution (the target:
at most 1.25x), and the inverted elements (signed volume <= 0) of the raw predictions over all
recorded steps. FE time per breast is the simulation's own record (both steps; the native
cohort's was measured when the cohort was built, possibly on another machine and load).
With ``--project``, each step's predicted trajectory is also moved onto valid shapes
(`mammo_net.validity.ValidityProjection`, predict.py's default) and scored again: last-step
error, inverted element-steps left and the projection's time per breast and step.

``--pool`` reads the per-breast rows of earlier runs' ``--out`` files (say, one per fold, each
scored by its own fold's models) and gives one table over all their breasts at the
``--factors`` resolutions, the ratios taken to the pooled native mean; it meshes, simulates
and predicts nothing. A breast that two files both score is refused.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from datamodules.graphs import MeshGraphDataModule
from fem.breasts.cohort_simulation import simulate_breast
from fem.breasts.mesh import Mesher
from fem.breasts.phantom import PhantomGenerator
from fem.breasts.pool import one_blas_thread, worker_pool
from fem.cohort import check_settings, make_breast
from fem.contract.atomic import write_json
from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from fem.engine.simulation import Simulation
from mammo_net.metrics import breast_rmse
from mammo_net.predictor import Surrogate, load_surrogate, predict_breast
from mammo_net.validity import ValidityProjection

RUNS = Path("results/cv/mesh_gnn")
NATIVE = "native"
#: The issue's target: the error at a finer resolution at most this times the native one.
TARGET_RATIO = 1.25
METRICS = (
    ("compression", "all_steps"),
    ("compression", "last_step"),
    ("unloaded", "all_steps"),
    ("unloaded", "last_step"),
)
#: The data settings that decide which breasts a model was trained on.
SPLIT_SETTINGS = ("split", "fold", "n_folds", "val_fraction", "seed")


def split_names(run: Path) -> tuple[list[str], list[str], dict]:
    """The training and validation breasts of ``run``'s split (the graph data module it was
    trained with, its own data folder only; its caches are reused when current) and the
    split's settings (`SPLIT_SETTINGS`)."""
    dm = MeshGraphDataModule.from_run(run)
    dm.prepare_data()
    dm.setup()
    split = {k: dm.hparams[k] for k in SPLIT_SETTINGS}
    return [b.name for b in dm.train if "@" not in b.name], [b.name for b in dm.val], split


def model_path(given: Path | None, step: str, split: dict) -> Path:
    """The model of ``step`` to evaluate: ``given``, or by default the committed graph model
    of the split's fold; refused when it was trained on another split than ``split`` (its
    training breasts could be among the evaluated ones)."""
    if given is None and split["fold"] is None:
        raise SystemExit(f"--{step}: the committed models are k-fold; name one for this split")
    path = given or RUNS / step / f"fold{split['fold']}" / "checkpoints" / "best.ckpt"
    data = torch.load(path, map_location="cpu", weights_only=True)
    trained = {k: (data.get("datamodule_hyper_parameters") or {}).get(k) for k in SPLIT_SETTINGS}
    if trained != split:
        raise SystemExit(
            f"{path}: trained on the split {trained}, but --split-run's validation breasts are "
            f"of {split}: some of them may be its training breasts"
        )
    return path


def cohort_settings(cohort: Path, factor: int) -> DictConfig:
    """The cohort's settings (``cohort_config.json``) with the mesher's element count and
    tolerance times ``factor``, as the cohort command's config (``simulate=true``)."""
    stored = json.loads((cohort / "cohort_config.json").read_text())
    if stored.get("refine", 0) or stored.get("variation") is not None:
        raise ValueError(
            f"{cohort}: a refined or varied cohort; this benchmark remeshes plain ones"
        )
    mesher = dict(stored["mesher"])
    mesher["target_elements"] = int(mesher["target_elements"] * factor)
    mesher["tolerance"] = int(mesher["tolerance"] * factor)
    return OmegaConf.create(
        {
            "generator": stored["generator"],
            "mesher": mesher,
            "simulation": stored["simulation"],
            "simulate": True,
            "refine": 0,
            "variation": None,
        }
    )


def fe_seconds(traj: Trajectory) -> float:
    """Both FE steps' time as the simulation recorded it, s."""
    return float(sum(traj.metadata["simulation"]["seconds"].values()))


def run_breast(
    generator: PhantomGenerator, mesher: Mesher, simulation: Simulation, name: str, folder: Path
) -> str | None:
    """Mesh and simulate breast ``name`` in ``folder`` unless done; the reason of a failure,
    or None."""
    mesh = folder / f"{name}.npz"
    out = folder / "trajectories"
    failed = out / f"{name}.failed.json"
    if failed.exists():
        row = json.loads(failed.read_text())
        return f"FE ({row['step']}): {row['reason']}"
    if (out / f"{name}.npz").exists():
        return None
    try:
        if not mesh.exists():
            make_breast(generator, mesher, int(name[1:5]), name[-1], folder, False)
        row = simulate_breast(simulation, mesh, out)
    except Exception as exc:  # a failed breast is reported, the benchmark goes on
        return f"{'FE' if mesh.exists() else 'meshing'}: {type(exc).__name__}: {exc}"
    if row["status"] != "ok":
        return f"FE ({row['step']}): {row['reason']}"
    return None


#: A worker process's generator, mesher and simulation per (cohort, factor), built once.
_BUILDS: dict[tuple[Path, int], tuple[PhantomGenerator, Mesher, Simulation]] = {}


@one_blas_thread
def run_task(cohort: Path, folder: Path, factor: int, name: str) -> str | None:
    """`run_breast` at ``factor`` in ``folder`` (a worker's task)."""
    if (cohort, factor) not in _BUILDS:
        cfg = cohort_settings(cohort, factor)
        _BUILDS[cohort, factor] = tuple(
            instantiate(c) for c in (cfg.generator, cfg.mesher, cfg.simulation)
        )
    return run_breast(*_BUILDS[cohort, factor], name, folder)


def simulate_resolutions(
    cohort: Path, out_root: Path, factors: list[int], names: list[str], workers: int = 1
) -> list[dict]:
    """Mesh and simulate every breast at every factor on ``workers`` processes (resumable);
    returns the failures."""
    folders = {}
    for factor in factors:
        folders[factor] = out_root / f"{factor}x"
        folders[factor].mkdir(parents=True, exist_ok=True)
        check_settings(folders[factor], cohort_settings(cohort, factor))
    tasks = [(name, factor) for name in names for factor in factors]
    failures = []
    with (
        worker_pool(workers) as pool,
        tqdm(total=len(tasks), unit="mesh", desc=f"FE -> {out_root}") as bar,
    ):
        futures = {
            pool.submit(run_task, cohort, folders[factor], factor, name): (name, factor)
            for name, factor in tasks
        }
        for future in as_completed(futures):
            name, factor = futures[future]
            reason = future.result()
            if reason is not None:
                failures.append({"breast": name, "factor": factor, "reason": reason})
                tqdm.write(f"FAILED {name} at {factor}x: {reason}")
            bar.set_postfix_str(f"{name} {factor}x")
            bar.update()
    return failures


def evaluate(
    traj: Trajectory,
    unloaded: Surrogate,
    compression: Surrogate,
    projection: ValidityProjection | None = None,
) -> dict:
    """One breast's errors (mm), inverted elements of the raw predictions and times; with
    ``projection``, also the errors and inverted elements after it and its time (s, per
    step's trajectory)."""
    thickness = float(traj.metadata["simulation"]["compressed_thickness_mm"])
    start = time.perf_counter()
    shapes = predict_breast(traj, unloaded, compression, [thickness])
    predict_s = time.perf_counter() - start
    from_fe = predict_breast(traj, None, compression, [thickness])  # the FE unloaded start
    row: dict = {"tetrahedra": traj.n_cells, "nodes": traj.n_nodes, "fe_s": fe_seconds(traj)}
    row["predict_s"] = predict_s
    for step, predicted, truth in (
        ("unloaded", shapes.unloaded, traj.unloaded),
        ("compression", from_fe.compressed[0], traj.compressed),
    ):
        row[step] = breast_rmse(predicted.transpose(1, 0, 2), truth.transpose(1, 0, 2))
        volume = signed_volume(predicted.astype(np.float64), traj.cells)  # (T, E)
        row[step]["inverted"] = int((volume <= 0).sum())
        row[step]["element_steps"] = int(volume.size)
        if projection is not None:
            start = time.perf_counter()
            valid = projection.project_step(traj, step, predicted)
            after = breast_rmse(valid.transpose(1, 0, 2), truth.transpose(1, 0, 2))
            volume = signed_volume(valid.astype(np.float64), traj.cells)
            after["inverted"] = int((volume <= 0).sum())
            after["seconds"] = time.perf_counter() - start
            row[step]["projected"] = after
    return row


def summary(rows: list[dict], resolutions: list[str]) -> list[dict]:
    """Per resolution: breasts, tetrahedra, FE time, mean errors and their ratio to native,
    inverted elements."""
    native = {
        m: np.mean([r[m[0]][m[1]] for r in rows if r["resolution"] == NATIVE]) for m in METRICS
    }
    out = []
    for res in resolutions:
        mine = [r for r in rows if r["resolution"] == res]
        entry: dict = {
            "resolution": res,
            "breasts": len(mine),
            "tetrahedra_median": statistics.median(r["tetrahedra"] for r in mine),
            "tetrahedra_range": [
                min(r["tetrahedra"] for r in mine),
                max(r["tetrahedra"] for r in mine),
            ],
            "fe_s_median": statistics.median(r["fe_s"] for r in mine),
            "predict_s_median": statistics.median(r["predict_s"] for r in mine),
        }
        for step, key in METRICS:
            mean = float(np.mean([r[step][key] for r in mine]))
            entry[f"{step}_{key}_mm"] = mean
            entry[f"{step}_{key}_ratio"] = mean / native[(step, key)]
        for step in ("compression", "unloaded"):
            if all("projected" in r[step] for r in mine):
                after = [r[step]["projected"] for r in mine]
                entry[f"{step}_projected_last_step_mm"] = float(
                    np.mean([a["last_step"] for a in after])
                )
                entry[f"{step}_projected_inverted"] = sum(a["inverted"] for a in after)
                entry[f"{step}_projection_s_median"] = statistics.median(
                    a["seconds"] for a in after
                )
            entry[f"{step}_inverted"] = sum(r[step]["inverted"] for r in mine)
            entry[f"{step}_inverted_breasts"] = sum(r[step]["inverted"] > 0 for r in mine)
            entry[f"{step}_element_steps"] = sum(r[step]["element_steps"] for r in mine)
        out.append(entry)
    return out


def markdown(table: list[dict]) -> str:
    """The summary as a Markdown table (error cells: mean over breasts, mm, and x native)."""
    lines = [
        "| resolution | breasts | tetrahedra: median (min-max) | FE s/breast (median)"
        " | compression RMSE, all steps | compression, last step | unloaded RMSE, all steps"
        " | unloaded, last step | inverted element-steps, compression / unloaded (breasts) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for e in table:
        errors = " | ".join(
            f"{e[f'{s}_{k}_mm']:.3f} mm ({e[f'{s}_{k}_ratio']:.2f}x)" for s, k in METRICS
        )
        lo, hi = e["tetrahedra_range"]
        lines.append(
            f"| {e['resolution']} | {e['breasts']} | {e['tetrahedra_median']:.0f} ({lo}-{hi}) | "
            f"{e['fe_s_median']:.1f} | {errors} | {e['compression_inverted']} / "
            f"{e['unloaded_inverted']} ({e['compression_inverted_breasts']} / "
            f"{e['unloaded_inverted_breasts']}) |"
        )
    if all("compression_projected_inverted" in e for e in table):
        lines += [
            "",
            "| resolution | after the validity projection: compression / unloaded, last step"
            " | inverted element-steps | projection s per breast (median) |",
            "| --- | --- | --- | --- |",
        ]
        for e in table:
            lines.append(
                f"| {e['resolution']} | {e['compression_projected_last_step_mm']:.3f} / "
                f"{e['unloaded_projected_last_step_mm']:.3f} mm | "
                f"{e['compression_projected_inverted']} / {e['unloaded_projected_inverted']} | "
                f"{e['compression_projection_s_median']:.2f} / "
                f"{e['unloaded_projection_s_median']:.2f} |"
            )
    worst = max(e[f"{s}_{k}_ratio"] for e in table for s, k in METRICS)
    verdict = "met" if worst <= TARGET_RATIO else "missed"
    lines += ["", f"Worst ratio to native: {worst:.2f}x (target <= {TARGET_RATIO}x: {verdict})."]
    return "\n".join(lines)


def pooled_rows(files: list[Path], resolutions: list[str]) -> list[dict]:
    """The per-breast rows of several ``--out`` files at ``resolutions``, of the breasts
    scored at all of them.

    Raises
    ------
    SystemExit
        A file is unreadable or has no per-breast rows, or two files score the same breast;
        the message names the file.
    """
    rows: list[dict] = []
    owner: dict[str, Path] = {}
    for path in files:
        try:
            breasts = json.loads(path.read_text())["breasts"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"{path}: not a resolution benchmark's --out file ({exc})") from exc
        mine = [r for r in breasts if r.get("resolution") in resolutions]
        scored: dict[str, set[str]] = {}
        for r in mine:
            scored.setdefault(r["breast"], set()).add(r["resolution"])
        for name in scored:
            if name in owner:
                raise SystemExit(f"{path}: breast {name} is also scored in {owner[name]}")
            owner[name] = path
        done = {n for n, res in scored.items() if res >= set(resolutions)}
        rows += [r for r in mine if r["breast"] in done]
    if not rows:
        raise SystemExit(f"{', '.join(map(str, files))}: no breast scored at {resolutions}")
    return rows


def write_report(path: Path, settings: dict, table: list[dict], failures: list, rows: list) -> None:
    """The summary and per-breast rows as JSON, atomically."""
    settings = {k: str(v) for k, v in settings.items()}
    write_json(
        {"settings": settings, "summary": table, "failures": failures, "breasts": rows}, path
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    for step in ("unloaded", "compression"):
        ap.add_argument(
            f"--{step}", type=Path, default=None,
            help=f"the {step} model (default: the split's fold of results/cv/mesh_gnn)",
        )  # fmt: skip
    ap.add_argument(
        "--split-run", type=Path, default=RUNS / "compression/fold0",
        help="train.py run folder whose validation breasts are used",
    )  # fmt: skip
    ap.add_argument("--cohort", type=Path, default=Path("data/cohort/full"))
    ap.add_argument("--out-root", type=Path, default=Path("data/resolution"))
    ap.add_argument("--factors", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--limit", type=int, default=None, help="the first breasts only")
    ap.add_argument(
        "--train-breasts", type=int, default=0,
        help="also mesh and simulate this many training breasts (for data.augment_dir)",
    )  # fmt: skip
    ap.add_argument("--workers", type=int, default=1, help="processes for meshing and FE")
    ap.add_argument(
        "--project", action="store_true",
        help="also score the predictions after the validity projection (predict.py's default)",
    )  # fmt: skip
    ap.add_argument(
        "--no-evaluate", action="store_true", help="mesh and simulate only; predict nothing"
    )  # fmt: skip
    ap.add_argument(
        "--no-simulate", action="store_true",
        help="evaluate the breasts already simulated; mesh and simulate nothing",
    )  # fmt: skip
    ap.add_argument("--out", type=Path, default=None, help="summary and per-breast rows as JSON")
    ap.add_argument(
        "--pool", type=Path, nargs="+", default=None,
        help="one table over these --out files' breasts; nothing is simulated or predicted",
    )  # fmt: skip
    args = ap.parse_args()
    if any(f < 2 for f in args.factors):
        raise SystemExit(f"--factors must be integers >= 2, got {args.factors}")
    if args.pool:
        resolutions = [NATIVE] + [f"{f}x" for f in args.factors]
        rows = pooled_rows(args.pool, resolutions)
        table = summary(rows, resolutions)
        print(f"{len(rows) // len(resolutions)} breasts from {len(args.pool)} files")
        print(markdown(table))
        if args.out:
            write_report(args.out, vars(args), table, [], rows)
        return
    if args.train_breasts < 0:
        raise SystemExit(f"--train-breasts must be >= 0, got {args.train_breasts}")
    train, names, split = split_names(args.split_run)
    if not args.no_evaluate:
        args.unloaded = model_path(args.unloaded, "unloaded", split)
        args.compression = model_path(args.compression, "compression", split)
    if args.train_breasts > len(train):
        raise SystemExit(f"--train-breasts: the split has {len(train)} training breasts")
    names = names[: args.limit]
    spaced = np.linspace(0, len(train) - 1, args.train_breasts).round().astype(int)
    failures = []
    if not args.no_simulate:
        failures = simulate_resolutions(
            args.cohort,
            args.out_root,
            args.factors,
            names + [train[i] for i in sorted(set(spaced.tolist()))],
            args.workers,
        )
    if args.no_evaluate:
        for f in failures:
            print(f"failed: {f['breast']} at {f['factor']}x: {f['reason']}")
        return
    folders = {NATIVE: args.cohort / "trajectories"}
    folders |= {f"{f}x": args.out_root / f"{f}x" / "trajectories" for f in args.factors}
    paired = [n for n in names if all((d / f"{n}.npz").exists() for d in folders.values())]
    print(
        f"{len(paired)} of {len(names)} breasts finished at every resolution ({', '.join(folders)})"
    )
    for f in failures:
        print(f"failed: {f['breast']} at {f['factor']}x: {f['reason']}")
    if not paired:
        raise SystemExit("no breast finished at every resolution")
    projection = ValidityProjection() if args.project else None
    unloaded = load_surrogate(args.unloaded, "unloaded")
    compression = load_surrogate(args.compression, "compression")
    rows = []
    for name in tqdm(paired, unit="breast", desc="predict"):
        for res, folder in folders.items():
            traj = Trajectory.load(folder / f"{name}.npz")
            rows.append(
                {
                    "breast": name,
                    "resolution": res,
                    **evaluate(traj, unloaded, compression, projection),
                }
            )
    table = summary(rows, list(folders))
    print(markdown(table))
    if args.out:
        write_report(args.out, vars(args), table, failures, rows)


if __name__ == "__main__":
    main()
