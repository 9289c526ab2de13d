"""Does a surrogate generalise to simulation conditions it was not trained on? The validation
breasts of train.py runs trained with ``data.train_conditions`` (bounds on the stiffness,
friction or mlo angle of the training breasts; the validation breasts are all kept) are
grouped into those inside the bounds ("in range") and those outside ("held out"), and by view
(cc, mlo); the table gives each group's per-breast RMSE and the ratio held out / in range of
the mean (the issue's target for the cohort v2: at most 1.25x).

    python benchmarks/conditions_generalisation.py 'results/cv_v2/mesh_gnn/compression/fold*'
    python benchmarks/conditions_generalisation.py RUN [RUN ...] --model xgboost \
        --bounds '{"young_fat": [700, 2600], "young_gland": [1600, 5900]}' --out outputs/mine

Each run folder is a finished train.py run (its ``results.md`` written; k-fold folds of one
cross-validation, one step) with ``predictions/<model>.npz`` (predicted from the run's model
files when missing, `mammo_net.predictor.predict_run`). The model is by default the run's network (its
``model._target_``: ``mesh_gnn``, ``att_blstm``), the bounds by default each run's own
``data.train_conditions``; both are read from the plain values of ``.hydra/config.yaml``,
nothing in it is instantiated. A breast's error is the report's (`mammo_net.report_data.collect`,
`mammo_net.report.breast_errors`): the mean node RMSE over all recorded steps and at the last
one, mm; its conditions are those its trajectory records (``metadata["simulation"]``). The
last-step error is also given relative to how far the breast's FE nodes move in the step (RMS
over nodes, from the prone shape for the unloaded state, from the unloaded state for the
compression): softer breasts move further, and that ratio discounts it.

The ratio is also given per run (one fold's held-out group is a few dozen breasts, so it is
noisy), and against a control when ``--control`` names the JSON this benchmark wrote for
another model on the same breasts (a model blind to the materials, e.g. XGBoost on the
paper's features): the control's ratio on the breasts both scored measures how hard the
held-out group is for reasons other than its stiffness, and the model's ratio over it is the
"controlled" ratio.

    python benchmarks/conditions_generalisation.py 'results/cv_v2/mesh_gnn/unloaded/fold*' \
        --control results/cv_v2/xgboost_unloaded.json --out results/cv_v2

Writes ``<out>/<model>_<step>.md`` (the tables, also printed) and ``.json`` (settings, groups,
ratios, per-run ratios and the per-breast rows), atomically.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

from omegaconf import OmegaConf

from datamodules.splits import check_bounds, within_bounds
from datamodules.trajectories import TrajectoryDataModule
from fem.contract.atomic import atomic_path, writable_folder
from mammo_net.metrics import summarize
from mammo_net.module import NETWORKS
from mammo_net.report import breast_errors
from mammo_net.report_data import collect

#: The issue's target: the held-out breasts' mean error at most this times the in-range one.
TARGET_RATIO = 1.25
VIEWS = ("all", "cc", "mlo")
RANGES = ("all", "in range", "held out")
METRICS = ("all_steps", "last_step")
#: A breast's last-step error over how far its FE nodes move in the step (RMS, both mm): the
#: held-out ratio of it discounts that softer breasts move further (not the issue's target).
RELATIVE = "last_step_relative"

Bounds = dict[str, tuple[float, float]]


def run_network(run: Path) -> str:
    """The network a run folder trained (`mammo_net.module.NETWORKS`), from the plain value
    ``model._target_`` of its ``.hydra/config.yaml``."""
    config = run / ".hydra" / "config.yaml"
    try:
        target = OmegaConf.load(config).model._target_
    except Exception as exc:  # a missing file or section, YAML
        raise ValueError(f"{config}: unreadable field 'model._target_' ({exc})") from exc
    names = {f"{c.__module__}.{c.__qualname__}": name for name, c in NETWORKS.items()}
    if target not in names:
        raise ValueError(
            f"{config}: field 'model._target_' is {target!r}, none of the networks "
            f"{sorted(names)}; name the model with --model"
        )
    return names[target]


def run_rows(run: Path, model: str, bounds: Bounds | None) -> tuple[str, Bounds, list[dict]]:
    """(step, bounds, per-breast rows) of one run: each validation breast's errors (mm), view,
    conditions and whether they lie outside ``bounds`` (default: the run's own).

    Raises
    ------
    ValueError
        The run has no ``results.md``: train.py writes it last, so the run is still training
        (or was killed), and predicting it would use a partial checkpoint.
    """
    if not (run / "results.md").is_file():
        raise ValueError(
            f"{run / 'results.md'}: not found: train.py has not finished this run (it writes "
            "results.md last); a run still training would be predicted from a partial checkpoint"
        )
    dm = TrajectoryDataModule.from_run(run)
    config = run / ".hydra" / "config.yaml"
    bounds = bounds if bounds is not None else dm.bounds
    if not bounds:
        raise ValueError(
            f"{config}: field 'data.train_conditions' sets no bounds (the run trained on every "
            "condition); give --bounds"
        )
    (evaluation,) = collect([run])  # one run: one (split, step)
    result = evaluation.models.get(model)
    if result is None:
        raise ValueError(
            f"{run / 'predictions' / model}.npz: not found (the run's predictions: "
            f"{', '.join(sorted(evaluation.models)) or 'none'})"
        )
    rows = []
    for name, errors in sorted(breast_errors(result, evaluation.truth).items()):
        truth = evaluation.truth[name]
        if truth.conditions is None:
            raise ValueError(
                f"{truth.path}: metadata field 'simulation' does not record the conditions "
                "(materials, friction, view, angle)"
            )
        if not truth.motion > 0:
            raise ValueError(f"{truth.path}: field {evaluation.step!r}: the FE nodes do not move")
        rows.append(
            {
                "run": str(run),
                "breast": name,
                "view": truth.conditions["view"],
                "held_out": not within_bounds(truth.conditions, bounds),
                "all_steps": errors["all_steps"],
                "last_step": errors["last_step"],
                "motion": truth.motion,
                RELATIVE: errors["last_step"] / truth.motion,
                "conditions": truth.conditions,
            }
        )
    return evaluation.step, bounds, rows


def summary(rows: list[dict]) -> dict:
    """Per (view, range) group: breasts and the mean, median, std of each metric (mm); per
    view and metric: held-out mean / in-range mean (None without breasts on either side)."""
    groups = []
    for view in VIEWS:
        for part in RANGES:
            mine = [
                r
                for r in rows
                if view in ("all", r["view"])
                and (part == "all" or r["held_out"] == (part == "held out"))
            ]
            group: dict = {"view": view, "range": part, "n": len(mine)}
            for m in METRICS:
                group[m] = summarize([r[m] for r in mine]) if mine else None
            groups.append(group)
    ratios = []
    for view in VIEWS:
        mine = [r for r in rows if view in ("all", r["view"])]
        ratios.append({"view": view, **{m: held_out_ratio(mine, m) for m in (*METRICS, RELATIVE)}})
    return {"groups": groups, "ratios": ratios}


def held_out_ratio(rows: list[dict], metric: str) -> float | None:
    """Mean ``metric`` of the held-out rows over that of the in-range rows (None without
    rows on either side)."""
    held = [r[metric] for r in rows if r["held_out"]]
    inside = [r[metric] for r in rows if not r["held_out"]]
    return sum(held) / len(held) / (sum(inside) / len(inside)) if held and inside else None


def run_ratios(rows: list[dict], control: list[dict] | None = None) -> list[dict]:
    """The held-out / in-range ratio over all runs and per run, with the breast counts; with
    the per-breast rows of a ``control`` model, also its ratio on the breasts both scored
    (each breast grouped as in ``rows``) and the model's ratio over it ("controlled").

    Raises
    ------
    ValueError
        The control scored none of the breasts.
    """
    theirs = {(r["breast"], r["view"]): r for r in control or []}
    if control is not None:
        rows = [r for r in rows if (r["breast"], r["view"]) in theirs]
        if not rows:
            raise ValueError("--control: it scored none of these breasts (matched by breast, view)")
    entries = []
    for run in ("all", *dict.fromkeys(r["run"] for r in rows)):
        mine = [r for r in rows if run in ("all", r["run"])]
        entry: dict = {
            "run": run,
            "in_range": sum(not r["held_out"] for r in mine),
            "held_out": sum(r["held_out"] for r in mine),
        }
        # the control's rows of these breasts, grouped as the model's
        paired = [
            {**theirs[r["breast"], r["view"]], "held_out": r["held_out"]} for r in theirs and mine
        ]
        for m in METRICS:
            entry[m] = ratio = held_out_ratio(mine, m)
            if control is not None:
                entry[f"control_{m}"] = base = held_out_ratio(paired, m)
                entry[f"controlled_{m}"] = ratio / base if ratio and base else None
        entries.append(entry)
    return entries


def markdown(table: dict, model: str, step: str) -> str:
    """The groups and ratios as Markdown tables, with the verdict on `TARGET_RATIO`."""
    lines = [
        f"| view | conditions | breasts | {model}, {step}: all steps (mean, median) +- std, mm"
        " | last step (mean, median) +- std, mm |",
        "| --- | --- | --- | --- | --- |",
    ]
    for g in table["groups"]:
        cells = [
            f"({g[m]['mean']:.3f}, {g[m]['median']:.3f}) +- {g[m]['std']:.3f}" if g[m] else "-"
            for m in METRICS
        ]
        lines.append(f"| {g['view']} | {g['range']} | {g['n']} | {cells[0]} | {cells[1]} |")
    lines += [
        "",
        "| view | held out / in range, all steps | last step | last step relative to the motion |",
        "| --- | --- | --- | --- |",
    ]
    for r in table["ratios"]:
        cells = [f"{r[m]:.2f}x" if r[m] is not None else "-" for m in (*METRICS, RELATIVE)]
        lines.append(f"| {r['view']} | " + " | ".join(cells) + " |")
    controlled = "control_all_steps" in table["runs"][0]
    head = " | control, all / last | controlled, all / last" if controlled else ""
    lines += [
        "",
        f"| runs | breasts in range / held out | held out / in range, all / last{head} |",
        "| --- | --- | --- |" + (" --- | --- |" if controlled else ""),
    ]
    for r in table["runs"]:
        cells = [f"{r['in_range']} / {r['held_out']}", ratio_pair(r, "")]
        if controlled:
            cells += [ratio_pair(r, "control_"), ratio_pair(r, "controlled_")]
        lines.append(f"| {r['run']} | " + " | ".join(cells) + " |")
    known = [r[m] for r in table["ratios"] for m in METRICS if r[m] is not None]
    if known:
        worst = max(known)
        verdict = "met" if worst <= TARGET_RATIO else "missed"
        lines += ["", f"Worst ratio: {worst:.2f}x (target <= {TARGET_RATIO}x: {verdict})."]
    else:
        lines += ["", "No ratio: no view has validation breasts both in range and held out."]
    return "\n".join(lines) + "\n"


def ratio_pair(entry: dict, prefix: str) -> str:
    """``entry``'s ratios ``<prefix>all_steps`` and ``<prefix>last_step``, e.g. ``1.02x / 0.97x``."""
    return " / ".join(
        "-" if entry[f"{prefix}{m}"] is None else f"{entry[f'{prefix}{m}']:.2f}x" for m in METRICS
    )


def read_control(path: Path) -> list[dict]:
    """The per-breast rows of a JSON this benchmark wrote (``--control``).

    Raises
    ------
    ValueError
        Not such a file; the message names it and the field.
    """
    try:
        rows = json.loads(path.read_text())["breasts"]
        return [
            {"breast": r["breast"], "view": r["view"], **{m: float(r[m]) for m in METRICS}}
            for r in rows
        ]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(
            f"{path}: not a conditions_generalisation JSON (field 'breasts' with breast, view, "
            f"{', '.join(METRICS)}): {exc!r}"
        ) from exc


def evaluate(
    patterns: list[str],
    model: str | None,
    bounds: Bounds | None,
    out: Path,
    control: Path | None = None,
) -> tuple[Path, Path]:
    """The tables of the run folders ``patterns`` (glob patterns allowed) into ``out``, with
    the ratios against the ``control`` JSON when given; returns the Markdown and JSON files."""
    control_rows = read_control(control) if control is not None else None
    runs = [Path(p) for pattern in patterns for p in sorted(glob.glob(pattern))]
    if not runs:
        raise FileNotFoundError(f"runs: no run folder matches {patterns}")
    writable_folder(out)
    if model is None:
        networks = {run: run_network(run) for run in runs}
        if len(set(networks.values())) > 1:
            raise ValueError(f"runs of different networks {networks}; name one with --model")
        model = networks[runs[0]]
    steps, settings, rows = {}, {}, []
    for run in runs:
        step, bounds_of_run, mine = run_rows(run, model, bounds)
        steps[str(run)] = step
        settings[str(run)] = {name: list(pair) for name, pair in bounds_of_run.items()}
        seen = {r["breast"]: r["run"] for r in rows}
        for r in mine:
            if r["breast"] in seen:
                raise ValueError(
                    f"{run}: breast {r['breast']} was already evaluated in {seen[r['breast']]}"
                )
        rows += mine
    if len(set(steps.values())) > 1:
        raise ValueError(f"runs of different steps {steps}; evaluate each step on its own")
    step = steps[str(runs[0])]
    table = {**summary(rows), "runs": run_ratios(rows, control_rows)}
    text = markdown(table, model, step)
    print(text)
    report = {
        "model": model,
        "step": step,
        "bounds": settings,
        "target_ratio": TARGET_RATIO,
        "control": None if control is None else str(control),
        **table,
        "breasts": rows,
    }
    files = out / f"{model}_{step}.md", out / f"{model}_{step}.json"
    with atomic_path(files[0]) as tmp:
        tmp.write_text(text)
    with atomic_path(files[1]) as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    return files


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("runs", nargs="+", help="train.py run folders (glob patterns allowed)")
    ap.add_argument("--model", default=None, help="predictions/<model>.npz; default the network")
    ap.add_argument(
        "--bounds", default=None,
        help='JSON {condition: [low, high]}; default each run\'s data.train_conditions',
    )  # fmt: skip
    ap.add_argument(
        "--out", type=Path, default=Path("outputs/conditions_generalisation"),
        help="folder of <model>_<step>.md and .json",
    )  # fmt: skip
    ap.add_argument(
        "--control", type=Path, default=None,
        help="this benchmark's JSON of a control model on the same breasts",
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        bounds = check_bounds(json.loads(args.bounds)) if args.bounds is not None else None
    except ValueError as exc:  # JSON or bounds
        raise SystemExit(f"--bounds: {exc}") from exc
    try:
        files = evaluate(args.runs, args.model, bounds, args.out, args.control)
    except (ValueError, FileNotFoundError) as exc:
        raise SystemExit(f"error: {exc}") from exc
    print("written:", *files)


if __name__ == "__main__":
    main()
