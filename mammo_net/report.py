"""The evaluation report: the reference paper's tables and figures, and more, from saved
predictions, without retraining.

    python -m mammo_net.report                                  # the cross-validation and one-fold runs
    python -m mammo_net.report 'runs=[outputs/train/2026-11-23_20-00-00]' out_dir=outputs/report/mine

Every run folder (a ``train.py`` run, or one fold of a ``-m data.fold=0,...,9`` sweep) holds
``predictions/<model>.npz`` for its validation breasts, or the model files to predict them
with (`mammo_net.predictor.predict_run`), and its ``.hydra/config.yaml``, which says the
simulation step, the trajectory folder and the split. Runs of the same split and
step are merged (the folds of a cross-validation cover the cohort once) and compared with the
FE trajectories. ``out_dir`` receives ``report.md`` (every table), ``report.json`` (every
number), ``per_breast.csv``, ``per_step.csv`` and ``figures/*.png``.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict
from itertools import combinations
from pathlib import Path

import hydra
import numpy as np
from hydra.utils import instantiate
from numpy.typing import NDArray
from omegaconf import DictConfig

from fem import CONFIG_DIR
from fem.contract.atomic import atomic_path, writable_folder
from mammo_net import evaluation as ev
from mammo_net import report_figures as figures
from mammo_net.metrics import summarize, summarize_breasts
from mammo_net.report_data import (
    TISSUE_CODES,
    BreastTruth,
    Evaluation,
    ModelResult,
    collect,
    ratio_curve,
)
from mammo_net.validity import ValidityProjection


def breast_errors(result: ModelResult, truth: dict[str, BreastTruth]) -> dict[str, dict]:
    """Per breast: ``all_steps`` and ``last_step`` RMSE, ``surface_*`` (skin nodes) and the
    error at each step (mm)."""
    out = {}
    for name, e in result.errors.items():
        skin = truth[name].surface
        out[name] = {
            "all_steps": float(e.mean()),
            "last_step": float(e[:, -1].mean()),
            "surface_all_steps": float(e[skin].mean()) if skin.any() else float("nan"),
            "surface_last_step": float(e[skin, -1].mean()) if skin.any() else float("nan"),
            "per_step": e.mean(0),
        }
    return out


def model_summary(
    result: ModelResult,
    truth: dict[str, BreastTruth],
    ratio_of_interest: float,
) -> dict[str, float]:
    """Every scalar of one model on one (split, step): the paper's and the extra ones."""
    per = breast_errors(result, truth)
    names = list(per)
    out = summarize_breasts([per[n] for n in names])
    for key in ("surface_all_steps", "surface_last_step"):
        out.update({f"{key}_{k}": v for k, v in summarize([per[n][key] for n in names]).items()})
    nodes_all = np.concatenate([result.errors[n].mean(1) for n in names])  # node, all steps
    nodes_last = np.concatenate([result.errors[n][:, -1] for n in names])
    steps = np.concatenate([result.errors[n].ravel() for n in names])  # node x step
    out |= {
        "node_all_steps_p95": float(np.percentile(nodes_all, 95)),
        "node_last_step_p95": float(np.percentile(nodes_last, 95)),
        "node_step_p95": float(np.percentile(steps, 95)),
        "node_step_max": float(steps.max()),
        "n_breasts": len(names),
    }
    for tissue, code in TISSUE_CODES.items():
        e = np.concatenate([result.errors[n].mean(1)[truth[n].tissue_code == code] for n in names])
        mean, sd = ev.mean_sd(e) if len(e) else (float("nan"), float("nan"))
        mu, sigma = ev.lognormal_fit(e)
        out |= {f"{tissue}_mean": mean, f"{tissue}_std": sd, f"{tissue}_mu": mu}
        out |= {f"{tissue}_sigma": sigma, f"{tissue}_nodes": len(e)}
    if all(truth[n].compression_ratio is not None for n in names):
        at = np.array(
            [
                ev.value_at(truth[n].compression_ratio, per[n]["per_step"], ratio_of_interest)
                for n in names
            ]
        )
        at = at[np.isfinite(at)]
        if len(at):
            out |= {f"at_ratio_{k}": v for k, v in summarize(at).items()}
            out["at_ratio_breasts"] = len(at)
    timed = [result.seconds[n] for n in names if n in result.seconds]
    if timed:
        out["predict_seconds_median"] = float(np.median(timed))
    return out


def ratio_fits(
    centres: NDArray, means: NDArray, linear_max: float
) -> dict[str, float | list[float]]:
    """exp2 fit over every bin, and the line over bins up to ``linear_max``, with r^2."""
    p, r2 = ev.fit_exp2(centres, means)
    below = centres <= linear_max
    line, line_r2 = ev.fit_line(centres[below], means[below])
    return {"exp2": p.tolist(), "exp2_r2": r2, "linear": line.tolist(), "linear_r2": line_r2}


def volume_correlation(result: ModelResult, truth: dict[str, BreastTruth]) -> float:
    """Pearson r between breast volume and all-steps breast RMSE (the paper's Fig. 15)."""
    names = list(result.errors)
    return ev.pearson_r(
        [truth[n].volume_cm3 for n in names], [result.errors[n].mean() for n in names]
    )


def paired_comparisons(e: Evaluation) -> dict[str, dict[str, dict[str, float]]]:
    """Each pair of models of ``e`` on the breasts both predicted: ``"A - B"`` ->
    ``all_steps`` / ``last_step`` -> `mammo_net.evaluation.paired_difference` of A against B."""
    per = {m: breast_errors(r, e.truth) for m, r in e.models.items()}
    out = {}
    for a, b in combinations(sorted(per), 2):
        names = sorted(set(per[a]) & set(per[b]))
        if names:
            out[f"{a} - {b}"] = {
                key: ev.paired_difference(
                    [per[a][n][key] for n in names], [per[b][n][key] for n in names]
                )
                for key in ("all_steps", "last_step")
            }
    return out


def keep_common_breasts(e: Evaluation) -> None:
    """Drop the breasts that not every model of ``e`` predicted (a paired comparison, e.g.
    while some folds of one model are still missing)."""
    common = set.intersection(*(set(r.errors) for r in e.models.values()))
    for r in e.models.values():
        r.errors = {n: v for n, v in r.errors.items() if n in common}
    e.truth = {n: t for n, t in e.truth.items() if n in common}


# --- tables --------------------------------------------------------------------------------


def _cell(s: dict, key: str) -> str:
    """``(mean, median) +- std`` of ``s[key_*]``, or ``-``."""
    if not np.isfinite(s.get(f"{key}_mean", np.nan)):
        return "-"
    return f"({s[f'{key}_mean']:.2f}, {s[f'{key}_median']:.2f}) +- {s[f'{key}_std']:.2f}"


def _tissue(s: dict, tissue: str) -> str:
    return (
        f"{s[f'{tissue}_mean']:.2f} +- {s[f'{tissue}_std']:.2f} "
        f"({s[f'{tissue}_mu']:.2f}, {s[f'{tissue}_sigma']:.2f})"
    )


def _paired(d: dict[str, float]) -> str:
    """``mean [95 % CI] (relative), A better in x %, p`` of a paired difference."""
    return (
        f"{d['mean_diff']:+.2f} [{d['ci95_low']:+.2f}, {d['ci95_high']:+.2f}] "
        f"({d['relative']:+.0%}); A better on {d['a_better']:.0%}; p = {d['wilcoxon_p']:.2g}"
    )


def _timing(fe: float, s: dict) -> list[str]:
    t = s.get("predict_seconds_median", float("nan"))
    speed_up = f"{fe / t:,.0f}x" if np.isfinite(fe / t) else "-"
    return [
        f"{fe:.1f}" if np.isfinite(fe) else "-",
        f"{t:.4f}" if np.isfinite(t) else "-",
        speed_up,
    ]


def _table(
    evaluations: list[Evaluation],
    header: Sequence[str],
    cells: Callable[[Evaluation, str], list[str]],
) -> str:
    """Markdown table: one row per (split, step, model), ``cells(evaluation, model)`` after."""
    lines = ["| " + " | ".join(["split", "step", "model", *header]) + " |"]
    lines.append("|" + " --- |" * (len(header) + 3))
    for e in evaluations:
        lines += ["| " + " | ".join([e.split, e.step, m, *cells(e, m)]) + " |" for m in e.models]
    return "\n".join(lines) + "\n"


def _paired_table(evaluations: list[Evaluation], paired: dict) -> str:
    """The paired-comparison table, or a line saying that no split has two models."""
    rows = [
        f"| {e.split} | {e.step} | {pair} | {d['all_steps']['n']} | "
        f"{_paired(d['all_steps'])} | {_paired(d['last_step'])} |\n"
        for e in evaluations
        for pair, d in paired[e.slug].items()
    ]
    if not rows:
        return "No split has two models to compare."
    return (
        "| split | step | A - B | breasts | all steps | last step |\n"
        "| --- | --- | --- | --- | --- | --- |\n" + "".join(rows)
    )


def markdown(evaluations: list[Evaluation], numbers: dict, analysis: DictConfig) -> str:
    """Every table of the report, in markdown."""
    s, fits, r = numbers["summary"], numbers["compression_ratio"], analysis.ratio_of_interest
    sections = [
        "# Evaluation report\n\nPer-breast RMSE (equation 2) of every model against the FE, mm, "
        + (
            "of the predictions as predicted (no projection)."
            if numbers.get("projection") is None
            else "of the predictions after the validity projection, as predict.py writes them "
            "(`mammo_net.validity.ValidityProjection`: "
            + ", ".join(f"{k} {v:g}" for k, v in numbers["projection"].items())
            + ")."
        ),
        "## Per-breast RMSE (paper Tables 3, 4, 7): (mean, median) +- std, mm",
        _table(
            evaluations,
            ["breasts", "all steps", "last step"],
            lambda e, m: [
                str(s[e.slug][m]["n_breasts"]),
                _cell(s[e.slug][m], "all_steps"),
                _cell(s[e.slug][m], "last_step"),
            ],
        ),
        "## Per tissue (paper Table 5): node RMSE over all steps, mean +- std (log-normal mu, "
        "sigma of ln RMSE), mm; interface nodes left out",
        _table(
            evaluations,
            [*TISSUE_CODES, "nodes (" + " / ".join(TISSUE_CODES) + ")"],
            lambda e, m: (
                [_tissue(s[e.slug][m], t) for t in TISSUE_CODES]
                + [" / ".join(str(s[e.slug][m][f"{t}_nodes"]) for t in TISSUE_CODES)]
            ),
        ),
        f"## Beyond the paper: node percentiles, skin nodes, error at {r:.0%} compression, mm\n\n"
        "p95 and max: over every node and step. Skin: per-breast RMSE of the skin nodes (what "
        f"image registration matches), (mean, median) +- std. At {r:.0%}: per-breast RMSE "
        "interpolated at that compression ratio, breasts compressed that far.",
        _table(
            evaluations,
            ["p95", "max", "skin, all steps", "skin, last step", f"at {r:.0%} ratio"],
            lambda e, m: [
                f"{s[e.slug][m]['node_step_p95']:.2f}",
                f"{s[e.slug][m]['node_step_max']:.2f}",
                _cell(s[e.slug][m], "surface_all_steps"),
                _cell(s[e.slug][m], "surface_last_step"),
                _cell(s[e.slug][m], "at_ratio"),
            ],
        ),
        "## Compression ratio and breast volume (paper Fig. 12, 13, 15)\n\n"
        "r^2 of the fits of the mean RMSE per 1 % compression-ratio bin (exp2: a exp(bx) + "
        f"c exp(dx); line: bins up to {analysis.linear_fit_max_ratio:.0%}); Pearson r between "
        "breast volume and all-steps RMSE.",
        _table(
            evaluations,
            ["exp2 r^2", "linear r^2", "volume: Pearson r"],
            lambda e, m: [
                f"{fits[e.slug][m]['exp2_r2']:.2f}" if e.slug in fits else "-",
                f"{fits[e.slug][m]['linear_r2']:.2f}" if e.slug in fits else "-",
                f"{numbers['volume_pearson_r'][e.slug][m]:.2f}",
            ],
        ),
        "## Beyond the paper: paired comparison, A - B on the breasts both predicted, mm\n\n"
        "Mean over breasts of the difference of per-breast RMSE [Student-t 95 % confidence "
        "interval] (relative to B's mean); the share of breasts where A's error is lower; "
        "two-sided Wilcoxon signed-rank p.",
        _paired_table(evaluations, numbers["paired"]),
        "## Time per breast (paper Table 6): FE solve against prediction, median, s\n\n"
        "FE: the solver's wall time recorded in each trajectory. Prediction: cached features "
        "to the node positions of every step, as timed when the predictions were saved.",
        _table(
            evaluations,
            ["FE (s)", "prediction (s)", "speed-up"],
            lambda e, m: _timing(numbers["timing"][e.slug], s[e.slug][m]),
        ),
    ]
    return "\n\n".join(sections)


def compute(evaluations: list[Evaluation], analysis: DictConfig) -> dict:
    """Every number of the report (the content of ``report.json``)."""
    numbers: dict = {"summary": {}, "compression_ratio": {}, "volume_pearson_r": {}}
    numbers["timing"], numbers["paired"] = {}, {}
    for e in evaluations:
        numbers["paired"][e.slug] = paired_comparisons(e)
        numbers["summary"][e.slug] = {
            m: model_summary(r, e.truth, analysis.ratio_of_interest) for m, r in e.models.items()
        }
        numbers["volume_pearson_r"][e.slug] = {
            m: volume_correlation(r, e.truth) for m, r in e.models.items()
        }
        fe = np.array([t.fe_seconds for t in e.truth.values()])
        numbers["timing"][e.slug] = (
            float(np.median(fe[np.isfinite(fe)])) if np.isfinite(fe).any() else float("nan")
        )
        if e.step == "compression":
            numbers["compression_ratio"][e.slug] = {
                m: ratio_fits(
                    *ratio_curve(r, e.truth, analysis.ratio_bin)[:2], analysis.linear_fit_max_ratio
                )
                for m, r in e.models.items()
            }
    return numbers


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def write_report(
    runs: Iterable[str | Path],
    out_dir: str | Path,
    analysis: DictConfig,
    data_dir: str | Path | None = None,
    exclude: Iterable[str | Path] = (),
    projection: ValidityProjection | None = None,
) -> Path:
    """Compute, tabulate and draw everything for the run folders ``runs`` (less those of
    ``exclude``) into ``out_dir``, with the settings ``analysis`` (``conf/analysis``), scoring
    the predictions after ``projection`` (None: as predicted); returns ``out_dir``.

    Every run folder, predictions file and trajectory is read, and ``out_dir`` checked, before
    the first file is written (`mammo_net.report_data.collect`)."""
    writable_folder(out_dir)
    evaluations = collect(runs, data_dir, exclude, projection)
    if analysis.get("common_breasts"):
        for e in evaluations:
            keep_common_breasts(e)
    out = Path(out_dir)
    numbers = compute(evaluations, analysis)
    numbers["projection"] = None if projection is None else asdict(projection)
    breast_rows, step_rows = [], []
    for e in evaluations:
        for m, r in e.models.items():
            for name, b in breast_errors(r, e.truth).items():
                t = e.truth[name]
                ratio = t.compression_ratio[-1] if t.compression_ratio is not None else ""
                breast_rows.append(
                    (e.split, e.step, m, name, f"{b['all_steps']:.4f}", f"{b['last_step']:.4f}",
                     f"{b['surface_all_steps']:.4f}", f"{b['surface_last_step']:.4f}",
                     f"{t.volume_cm3:.1f}", ratio and f"{ratio:.4f}", f"{t.fe_seconds:.2f}",
                     f"{r.seconds.get(name, float('nan')):.5f}")
                )  # fmt: skip
            per_step = np.stack([err.mean(0) for err in r.errors.values()])  # (breasts, T)
            for k, col in enumerate(per_step.T):
                step_rows.append((e.split, e.step, m, k + 1, f"{col.mean():.4f}",
                                  f"{np.median(col):.4f}", f"{np.percentile(col, 95):.4f}"))  # fmt: skip
    figures.draw_all(evaluations, numbers, analysis, out / "figures")
    write_csv(
        out / "per_breast.csv",
        ["split", "step", "model", "breast", "rmse_all_steps_mm", "rmse_last_step_mm",
         "skin_all_steps_mm", "skin_last_step_mm", "volume_cm3", "final_compression_ratio",
         "fe_seconds", "predict_seconds"],
        breast_rows,
    )  # fmt: skip
    write_csv(
        out / "per_step.csv",
        ["split", "step", "model", "recorded_step", "mean_mm", "median_mm", "p95_mm"],
        step_rows,
    )
    with atomic_path(out / "report.json") as tmp:
        tmp.write_text(json.dumps(numbers, indent=1, default=float))
    text = markdown(evaluations, numbers, analysis)
    with atomic_path(out / "report.md") as tmp:
        tmp.write_text(text)
    return out


@hydra.main(config_path=CONFIG_DIR, config_name="report", version_base="1.3")
def main(cfg: DictConfig) -> None:
    projection = instantiate(cfg.projection) if cfg.get("projection") else None
    out = write_report(cfg.runs, cfg.out_dir, cfg.analysis, cfg.data_dir, cfg.exclude, projection)
    print((out / "report.md").read_text())


if __name__ == "__main__":
    main()
