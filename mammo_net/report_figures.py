"""The figures of the evaluation report (`mammo_net.report`), as PNG files readable on their own:
titles say the split, step and quantity, axes carry units, legends carry the fitted numbers."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from fem.breasts.figures import plt, save_png, shapes_sections_png
from fem.contract.trajectory import Trajectory
from mammo_net import evaluation as ev
from mammo_net.inference import load_predictions
from mammo_net.report_data import TISSUE_CODES, Evaluation, ranked_breasts, ratio_curve

COLOURS = {"att_blstm": "#d62728", "xgboost": "#1f77b4", "ert": "#2ca02c"}


def colour(model: str, index: int) -> str:
    return COLOURS.get(model, f"C{index + 3}")


def finish(fig, ax, xlabel: str, ylabel: str, title: str, path: Path, fontsize: int = 8) -> Path:
    """Label a one-panel figure, add its grid and legend, and save it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=fontsize)
    return save_png(fig, path)


def error_classes_png(evaluations: Sequence[Evaluation], step: str, path: Path) -> Path:
    """Percentage of nodes per 2 mm error class, all steps and last step, every split and
    model of ``step`` side by side (paper Fig. 4, 11, 22, 23)."""
    bars = [(e, m) for e in evaluations if e.step == step for m in e.models]
    labels = ev.error_class_labels()
    x = np.arange(len(labels))
    width = 0.8 / len(bars)
    fig, axes = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True)
    for ax, which in zip(axes, ("all steps", "last step"), strict=True):
        for i, (e, m) in enumerate(bars):
            errors = [
                v.mean(1) if which == "all steps" else v[:, -1] for v in e.models[m].errors.values()
            ]
            pct = ev.error_classes(np.concatenate(errors))
            hatch = "//" if e.split == "one-fold" and len({b[0].split for b in bars}) > 1 else None
            ax.bar(x + (i - (len(bars) - 1) / 2) * width, pct, width, label=f"{m} ({e.split})",
                   color=colour(m, i), hatch=hatch, edgecolor="k", linewidth=0.3)  # fmt: skip
        ax.set_ylabel(f"nodes (%), node RMSE over {which}")
        ax.set_yscale("log")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[1].set_xticks(x, labels)
    axes[1].set_xlabel("node RMSE class (mm)")
    fig.suptitle(f"Percentage of nodes per error class: {step} step")
    return save_png(fig, path)


def compression_ratio_png(e: Evaluation, numbers: dict, analysis: DictConfig, path: Path) -> Path:
    """Mean RMSE per 1 % compression-ratio bin, its exp2 fit and the line up to 53 %
    (paper Fig. 12, 13)."""
    fits = numbers["compression_ratio"][e.slug]
    fig, ax = plt.subplots(figsize=(8, 5.5))
    for i, (m, r) in enumerate(e.models.items()):
        centres, means, _ = ratio_curve(r, e.truth, analysis.ratio_bin)
        f, c = fits[m], colour(m, i)
        ax.plot(100 * centres, means, "o", ms=3.5, color=c, label=f"{m}: bin means")
        grid = np.linspace(centres.min(), centres.max(), 200)
        if np.isfinite(f["exp2_r2"]):
            ax.plot(100 * grid, ev.exp2(grid, *f["exp2"]), "-", color=c,
                    label=f"{m}: exp2 fit, r$^2$ = {f['exp2_r2']:.2f}")  # fmt: skip
        if np.isfinite(f["linear_r2"]):
            line = grid[grid <= analysis.linear_fit_max_ratio]
            ax.plot(100 * line, np.polyval(f["linear"], line), "--", color=c,
                    label=f"{m}: linear fit to {analysis.linear_fit_max_ratio:.0%}, "
                    f"r$^2$ = {f['linear_r2']:.2f}")  # fmt: skip
    title = f"RMSE against compression ratio: {e.label}, {len(e.truth)} breasts"
    return finish(
        fig,
        ax,
        "compression ratio (%), 1 % bins",
        "mean breast RMSE at the step (mm)",
        title,
        path,
        7,
    )


def tissue_png(e: Evaluation, numbers: dict, path: Path) -> Path:
    """Histograms of node RMSE (all steps) per tissue with log-normal fits (paper Fig. 14)."""
    s = numbers["summary"][e.slug]
    fig, axes = plt.subplots(1, len(TISSUE_CODES), figsize=(14, 4.5))
    for ax, (tissue, code) in zip(axes, TISSUE_CODES.items(), strict=True):
        errors = {
            m: np.concatenate([v.mean(1)[e.truth[n].tissue_code == code] for n, v in r.errors.items()])
            for m, r in e.models.items()
        }  # fmt: skip
        top = max((np.percentile(v, 99.5) for v in errors.values() if len(v)), default=1.0)
        bins = np.linspace(0, top, 40)
        grid = np.linspace(top / 400, top, 300)
        for i, (m, v) in enumerate(errors.items()):
            if not len(v):
                continue
            mu, sigma = s[m][f"{tissue}_mu"], s[m][f"{tissue}_sigma"]
            label = f"{m}: $\\mu$ = {mu:.2f}, $\\sigma$ = {sigma:.2f}"
            ax.hist(v, bins=bins, density=True, alpha=0.3, color=colour(m, i), label=label)
            if sigma > 0:
                ax.plot(grid, ev.lognormal_pdf(grid, mu, sigma), color=colour(m, i))
        n = len(next(iter(errors.values())))
        ax.set_title(f"{tissue} ({n} nodes)")
        ax.set_xlabel("node RMSE over all steps (mm)")
        if n:
            ax.legend(fontsize=7)
    axes[0].set_ylabel("probability density (1/mm)")
    fig.suptitle(f"Node RMSE per tissue, log-normal fits (interface nodes left out): {e.label}")
    return save_png(fig, path)


def volume_png(e: Evaluation, numbers: dict, path: Path) -> Path:
    """Breast RMSE against breast volume with a linear fit and Pearson r (paper Fig. 15)."""
    fig, ax = plt.subplots(figsize=(8, 5.5))
    for i, (m, r) in enumerate(e.models.items()):
        volume = np.array([e.truth[n].volume_cm3 for n in r.errors])
        rmse = np.array([v.mean() for v in r.errors.values()])
        c = colour(m, i)
        rho = numbers["volume_pearson_r"][e.slug][m]
        ax.plot(volume, rmse, "o", ms=3, alpha=0.6, color=c, label=f"{m}: Pearson r = {rho:.2f}")
        if len(volume) > 1 and volume.std() > 0:
            p = np.polyfit(volume, rmse, 1)
            ax.plot(np.sort(volume), np.polyval(p, np.sort(volume)), "-", color=c)
    title = f"RMSE against breast volume: {e.label}"
    return finish(fig, ax, "breast volume (cm$^3$)", "breast RMSE over all steps (mm)", title, path)


def per_step_png(e: Evaluation, path: Path) -> Path:
    """Breast RMSE at each recorded step: mean, and the 5-95 % range over breasts."""
    fig, ax = plt.subplots(figsize=(8, 5))
    for i, (m, r) in enumerate(e.models.items()):
        per = np.stack([v.mean(0) for v in r.errors.values()])  # (breasts, T)
        t = np.arange(1, per.shape[1] + 1)
        ax.plot(t, per.mean(0), color=colour(m, i), label=f"{m}: mean")
        ax.fill_between(t, *np.percentile(per, [5, 95], axis=0), color=colour(m, i), alpha=0.15,
                        label=f"{m}: 5-95 % of breasts")  # fmt: skip
    title = f"Error per recorded step: {e.label}, {len(e.truth)} breasts"
    return finish(fig, ax, "recorded step", "breast RMSE at the step (mm)", title, path)


def sections_png(e: Evaluation, name: str, which: str, path: Path) -> Path:
    """FE against each model's final shape of breast ``name`` in the sagittal, axial and
    coronal planes through the FE shape's centroid, coloured by tissue (paper Fig. 5-10,
    16-21)."""
    traj = Trajectory.load(e.truth[name].path)
    shapes = {"FE (ground truth)": e.truth[name].positions[:, -1]}
    for m, r in e.models.items():
        rmse = e.models[m].errors[name][:, -1].mean()
        label = f"{m}, RMSE {rmse:.2f} mm at this step"
        shapes[label] = load_predictions(r.sources[name])[name][:, -1].astype(float)
    title = f"{which.capitalize()} breast {name}, last recorded step: {e.label}"
    return shapes_sections_png(traj.cells, traj.tissue, shapes, title, path)


def draw_all(
    evaluations: Sequence[Evaluation], numbers: dict, analysis: DictConfig, folder: Path
) -> list[Path]:
    """Every figure of the report into ``folder``."""
    out = [error_classes_png(evaluations, s, folder / f"error_classes_{s}.png")
           for s in sorted({e.step for e in evaluations})]  # fmt: skip
    for e in evaluations:
        out.append(tissue_png(e, numbers, folder / f"{e.slug}_tissue.png"))
        out.append(volume_png(e, numbers, folder / f"{e.slug}_volume.png"))
        out.append(per_step_png(e, folder / f"{e.slug}_per_step.png"))
        if e.slug in numbers["compression_ratio"]:
            out.append(
                compression_ratio_png(
                    e, numbers, analysis, folder / f"{e.slug}_compression_ratio.png"
                )
            )
        if analysis.sections:
            ranked = ranked_breasts(e)
            for which, name in (("best", ranked[0]), ("worst", ranked[-1])):
                out.append(sections_png(e, name, which, folder / f"{e.slug}_sections_{which}.png"))
    return out
