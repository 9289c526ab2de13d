"""Pictures: tissue-coloured body-plane sections of volumes and meshes, cohort histograms."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.colors import ListedColormap
from numpy.typing import NDArray

from fem.breasts.phantom import LabelVolume
from fem.contract.atomic import atomic_path
from fem.contract.quality import EDGES
from fem.contract.trajectory import Trajectory

#: Colours of background, fat, gland, muscle (as the paper: light fat, dark gland).
TISSUE_COLOURS = ["#ffffff", "#f6d8a8", "#1f4e9c", "#b5413b"]
TISSUE_NAMES = ["background", "fat", "gland", "muscle"]

#: Body planes: name -> (axis normal to the plane, (horizontal axis, vertical axis)), RAS+.
PLANES = {"sagittal": (0, (1, 2)), "axial": (2, (0, 1)), "coronal": (1, (0, 2))}
#: Axis labels: the coordinate and the body direction it grows to (patient's right, anterior,
#: superior), so that a wrongly oriented input shows in the figures.
AXIS_NAMES = ("x [mm] \u2192 right", "y [mm] \u2192 anterior", "z [mm] \u2192 superior")


def plane_section(
    points: NDArray, cells: NDArray, axis: int, value: float
) -> tuple[list[NDArray], NDArray[np.int64]]:
    """Polygons cut from the tetrahedra by the plane ``x[axis] = value``.

    Returns
    -------
    polygons : list of (3 or 4, 3) arrays
        Section polygon of each cut element, vertices ordered around its centroid.
    cut : (P,) int64
        Index of the element of each polygon.
    """
    s = points[cells][:, :, axis] - value  # (E, 4)
    cut = np.flatnonzero((s.min(1) < 0) & (s.max(1) > 0))
    polygons = []
    for e in cut:
        p, d = points[cells[e]], s[e]
        verts = [
            p[i] + d[i] / (d[i] - d[j]) * (p[j] - p[i])
            for i, j in EDGES
            if (d[i] < 0) != (d[j] < 0)
        ]
        verts = np.array(verts)
        c = verts.mean(0)
        h, v = [a for a in range(3) if a != axis]
        order = np.argsort(np.arctan2(verts[:, v] - c[v], verts[:, h] - c[h]))
        polygons.append(verts[order])
    return polygons, cut


def draw_mesh_section(
    ax: plt.Axes, points: NDArray, cells: NDArray, tissue: NDArray, plane: str, value: float
) -> None:
    """Fill the section of a tetrahedral mesh in ``plane`` at ``value`` with tissue colours."""
    axis, (h, v) = PLANES[plane]
    polygons, cut = plane_section(points, cells, axis, value)
    if polygons:
        colours = [TISSUE_COLOURS[int(t)] for t in tissue[cut]]
        ax.add_collection(
            PolyCollection(
                [p[:, [h, v]] for p in polygons],
                facecolors=colours,
                edgecolors="#444444",
                linewidths=0.3,
            )
        )
    ax.set_xlabel(AXIS_NAMES[h])
    ax.set_ylabel(AXIS_NAMES[v])
    ax.set_aspect("equal")


def draw_volume_section(ax: plt.Axes, volume: LabelVolume, plane: str, value: float) -> None:
    """Show the voxel labels of an axis-aligned volume in ``plane`` at ``value`` (mm)."""
    axis, (h, v) = PLANES[plane]
    spacing, origin = np.diag(volume.affine)[:3], volume.affine[:3, 3]
    index = int(
        np.clip(np.rint((value - origin[axis]) / spacing[axis]), 0, volume.labels.shape[axis] - 1)
    )
    img = np.take(volume.labels, index, axis=axis)  # axes (h, v) in increasing order
    extent = [
        origin[h] - spacing[h] / 2,
        origin[h] + (img.shape[0] - 0.5) * spacing[h],
        origin[v] - spacing[v] / 2,
        origin[v] + (img.shape[1] - 0.5) * spacing[v],
    ]
    ax.imshow(
        img.T,
        origin="lower",
        extent=extent,
        cmap=ListedColormap(TISSUE_COLOURS),
        vmin=0,
        vmax=3,
        interpolation="nearest",
    )
    ax.set_xlabel(AXIS_NAMES[h])
    ax.set_ylabel(AXIS_NAMES[v])


def breast_sections_png(
    traj: Trajectory, path: str | Path, volume: LabelVolume | None = None
) -> Path:
    """PNG of the sagittal, axial and coronal sections through the breast's centre.

    Top row: the segmentation (when ``volume`` is given); bottom row: the mesh, coloured by
    element tissue. Sections pass through the centroid of the breast (fat/gland) elements.
    """
    breast = traj.tissue != 3
    centre = traj.points[traj.cells[breast]].mean(axis=(0, 1))
    rows = 2 if volume is not None else 1
    fig, axes = plt.subplots(rows, 3, figsize=(13, 4.2 * rows), squeeze=False)
    lo, hi = traj.points.min(0) - 5, traj.points.max(0) + 5
    for col, plane in enumerate(PLANES):
        axis, (h, v) = PLANES[plane]
        if volume is not None:
            draw_volume_section(axes[0, col], volume, plane, centre[axis])
            axes[0, col].set_title(
                f"{plane} segmentation, {AXIS_NAMES[axis][0]} = {centre[axis]:.0f} mm"
            )
        ax = axes[-1, col]
        draw_mesh_section(ax, traj.points, traj.cells, traj.tissue, plane, centre[axis])
        ax.set_title(f"{plane} mesh section")
        for a in axes[:, col]:
            a.set_xlim(lo[h], hi[h])
            a.set_ylim(lo[v], hi[v])
    m = traj.metadata
    mesh = m.get("mesh", {})
    title = f"patient {m.get('patient', '?')} {m.get('laterality', '')}"
    if "breast_volume_cm3" in m:
        title += (
            f"  site {m['site']}  volume {m['breast_volume_cm3']:.0f} cm$^3$  "
            f"glandular {100 * m['glandular_fraction']:.1f} % (BI-RADS {m['density_category']})  "
            f"target compression {100 * m['target_compression_ratio']:.0f} %"
        )
    if mesh:
        q = mesh["quality"]
        title += (
            f"\n{mesh['n_elements']} tetrahedra, {mesh['n_nodes']} nodes, volume error "
            f"{100 * mesh['volume_error']:+.1f} %, min radius ratio {q['min_radius_ratio']:.2f}, "
            f"dihedral {q['min_dihedral_deg']:.0f}-{q['max_dihedral_deg']:.0f} deg"
        )
    fig.suptitle(title, fontsize=10)
    handles = [plt.Rectangle((0, 0), 1, 1, fc=c, ec="#444444") for c in TISSUE_COLOURS[1:]]
    fig.legend(handles, TISSUE_NAMES[1:], loc="lower center", ncol=3, frameon=False)
    # Fixed margins: tight_layout costs as much as drawing the figure.
    fig.subplots_adjust(
        left=0.06,
        right=0.99,
        bottom=0.1 if rows == 2 else 0.18,
        top=0.88 if rows == 2 else 0.78,
        wspace=0.3,
        hspace=0.3,
    )
    return save_png(fig, path)


def shapes_sections_png(
    cells: NDArray,
    tissue: NDArray,
    shapes: dict[str, NDArray],
    title: str,
    path: str | Path,
    centre: NDArray | None = None,
) -> Path:
    """Several node positions of one mesh (rows: ``{label: (N, 3)}``, mm) cut in the
    sagittal, axial and coronal planes (columns) through ``centre`` (default: the first
    shape's centroid), coloured by tissue, on common axes."""
    first = next(iter(shapes.values()))
    centre = first.mean(0) if centre is None else np.asarray(centre)
    stacked = np.concatenate(list(shapes.values()))
    lo, hi = stacked.min(0) - 5, stacked.max(0) + 5
    fig, axes = plt.subplots(len(shapes), 3, figsize=(13, 3.6 * len(shapes)), squeeze=False)
    for row, (label, points) in enumerate(shapes.items()):
        for col, (plane, (axis, (h, v))) in enumerate(PLANES.items()):
            ax = axes[row, col]
            draw_mesh_section(ax, points, cells, tissue, plane, centre[axis])
            ax.set_xlim(lo[h], hi[h])
            ax.set_ylim(lo[v], hi[v])
            ax.set_title(f"{label}: {plane}", fontsize=9)
    handles = [plt.Rectangle((0, 0), 1, 1, fc=c, ec="#444444") for c in TISSUE_COLOURS[1:]]
    fig.legend(handles, TISSUE_NAMES[1:], loc="upper right")
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return save_png(fig, path)


def cohort_summary_png(rows: Sequence[dict], path: str | Path) -> Path:
    """Histograms of breast volume, glandular fraction, compression ratio and element count,
    per site (rows: per-breast metadata dicts)."""
    panels = [
        ("breast volume [cm$^3$]", lambda r: r["breast_volume_cm3"], np.linspace(0, 2600, 27)),
        ("glandular fraction [%]", lambda r: 100 * r["glandular_fraction"], np.linspace(0, 36, 37)),
        (
            "target compression ratio [%]",
            lambda r: 100 * r["target_compression_ratio"],
            np.arange(0, 82, 4),
        ),
        ("tetrahedra per mesh", lambda r: r["mesh"]["n_elements"], np.arange(1950, 2560, 25)),
    ]
    sites = sorted({r["site"] for r in rows})
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    for ax, (label, get, bins) in zip(axes.ravel(), panels, strict=True):
        for s in sites:
            data = [get(r) for r in rows if r["site"] == s]
            weights = np.full(len(data), 100.0 / len(data))
            ax.hist(
                data,
                bins=bins,
                weights=weights,
                histtype="step",
                lw=1.8,
                label=f"site {s} ({len(data)} breasts)",
            )
        ax.set_xlabel(label)
        ax.set_ylabel("% of the site's breasts")
        if "glandular" in label:
            for x in (3.5, 7.5, 15.5):
                ax.axvline(x, color="k", lw=0.8, ls="--")
            for x, cat in zip((1.5, 5.5, 11.5, 25), "abcd", strict=True):
                ax.text(x, ax.get_ylim()[1] * 0.95, cat, ha="center", va="top")
    axes[0, 0].legend()
    fig.suptitle(
        f"Virtual cohort: {len({r['patient'] for r in rows})} patients, {len(rows)} breasts"
    )
    fig.tight_layout()
    return save_png(fig, path)


def save_png(fig: plt.Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` atomically (PNG, 90 dpi) and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path


def simulation_summary_png(rows: Sequence[dict], path: str | Path) -> Path:
    """The cohort simulation report: compression reached, run times and failures.

    Parameters
    ----------
    rows : sequence of dict
        One per simulated breast, with keys ``name`` (str), ``status`` (``"ok"`` or
        ``"failed"``), ``reason`` (str, ``""`` when ok), ``volume_cm3`` (float, cm^3),
        ``time_unloaded_s`` (float, s), ``time_compression_s`` (float, s; NaN when failed),
        ``compression_ratio`` (float, final ratio reached, 1 - gap / thickness; NaN when
        failed) and ``target_compression_ratio`` (float).
    path : str or Path
        Output PNG, written atomically.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Panels: histogram of the final compression ratios of the converged breasts (with their
    targets as an outline), histograms of the time per breast (unloaded-state step,
    compression step and their total), time against breast volume (failed breasts in red,
    at the time of their unloaded-state step), and the list of failures with their reasons.
    """
    ok = [r for r in rows if r["status"] == "ok"]
    failed = [r for r in rows if r["status"] != "ok"]

    def values(rs: Sequence[dict], get) -> NDArray[np.float64]:
        v = np.array([get(r) for r in rs], float)
        return v[np.isfinite(v)]

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))

    ax = axes[0, 0]
    reached = values(ok, lambda r: 100 * r["compression_ratio"])
    target = values(ok, lambda r: 100 * r["target_compression_ratio"])
    bins = np.arange(0, 102, 4)
    ax.hist(reached, bins=bins, color="#1f77b4", alpha=0.8, label="reached")
    ax.hist(target, bins=bins, histtype="step", color="k", lw=1.5, label="target")
    ax.set_xlabel("final compression ratio [%]")
    ax.set_ylabel("breasts")
    title = f"converged: {len(ok)} breasts"
    if reached.size:
        title += f", median {np.median(reached):.0f} %, max {reached.max():.0f} %"
    ax.set_title(title, fontsize=10)
    ax.legend()

    ax = axes[0, 1]
    t_unloaded = values(rows, lambda r: r["time_unloaded_s"])
    t_compression = values(ok, lambda r: r["time_compression_s"])
    t_total = values(ok, lambda r: r["time_unloaded_s"] + r["time_compression_s"])
    all_times = np.concatenate([t_unloaded, t_compression, t_total, [1.0]])
    bins = np.linspace(0, 1.05 * all_times.max(), 26)
    ax.hist(t_total, bins=bins, color="#2ca02c", alpha=0.6, label="total (converged)")
    ax.hist(t_unloaded, bins=bins, histtype="step", lw=1.8, label="unloaded-state step (all)")
    ax.hist(t_compression, bins=bins, histtype="step", lw=1.8, label="compression step")
    ax.set_xlabel("time per breast [s]")
    ax.set_ylabel("breasts")
    title = "time per breast"
    if t_total.size:
        title += f": median total {np.median(t_total):.0f} s, max {t_total.max():.0f} s"
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    ax.scatter(
        [r["volume_cm3"] for r in ok],
        [r["time_unloaded_s"] + r["time_compression_s"] for r in ok],
        s=18,
        color="#1f77b4",
        label=f"converged ({len(ok)}), total time",
    )
    if failed:
        ax.scatter(
            [r["volume_cm3"] for r in failed],
            [r["time_unloaded_s"] for r in failed],
            s=30,
            marker="x",
            color="red",
            label=f"failed ({len(failed)}), unloaded-state step time",
        )
    ax.set_xlabel("breast volume [cm$^3$]")
    ax.set_ylabel("time [s]")
    ax.set_title("time against breast volume", fontsize=10)
    ax.legend(fontsize=8)

    ax = axes[1, 1]
    ax.axis("off")
    lines = [f"failures: {len(failed)} of {len(rows)} breasts"]
    shown = 14
    lines += [f"{r['name']}: {r['reason'] or 'no reason given'}"[:70] for r in failed[:shown]]
    if len(failed) > shown:
        lines.append(f"... and {len(failed) - shown} more")
    ax.text(
        0.0,
        1.0,
        "\n".join(lines),
        transform=ax.transAxes,
        va="top",
        ha="left",
        family="monospace",
        fontsize=8,
        color="red" if failed else "k",
    )

    fig.suptitle(f"Simulation of {len(rows)} breasts: {len(ok)} converged, {len(failed)} failed")
    fig.tight_layout()
    return save_png(fig, path)
