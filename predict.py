"""Deformed meshes of a new breast from the trained surrogates, in milliseconds, without FE.

    python predict.py input=case01.vtu thickness=55 laterality=L \
        unloaded_model=<run>/checkpoints/last.ckpt compression_model=<run>/baselines/xgboost.json \
        [landmarks=lesions.csv] [out_dir=outputs/predict/case01] [reader.label_map.gland=[2,4]]

The input (a Trajectory, a tetrahedral mesh or a segmentation, meshed first), read by the
``reader`` group (`fem.breasts.io.BreastReader`), goes through the unloaded-state model, then
the compression model for each thickness (`mammo_net.predictor`).
Writes the final shapes (VTU, and the input's format where meshio writes it), every step as an
XDMF time series, a PNG preview in three body planes, the mapped landmarks (CSV, mm) and
``checks.json``: the prediction time and the physical checks of every shape
(`mammo_net.validity`: inverted elements, volume change, skin inside a plate), which also warn,
or refuse the output with ``checks.on_violation=refuse``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import hydra
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig, ListConfig

from fem.breasts.figures import shapes_sections_png
from fem.breasts.io import file_kind, file_suffix
from fem.contract.atomic import writable_folder, write_json
from fem.contract.trajectory import Trajectory
from mammo_net.predictor import (
    load_surrogate,
    map_landmarks,
    predict_breast,
    read_landmarks,
    write_rows,
    write_shapes,
)

LATERALITIES = ("L", "R")


def thicknesses(setting: object) -> list[float]:
    """The ``thickness`` setting (a number or a list of numbers) as compressed thicknesses, mm.

    Raises
    ------
    ValueError
        Not a number nor a non-empty list of numbers, or a thickness that is not finite and
        positive; the message names the setting.
    """
    values = list(setting) if isinstance(setting, ListConfig) else [setting]
    try:
        out = [float(t) for t in values]
    except (TypeError, ValueError):
        out = []
    if not out or not all(math.isfinite(t) and t > 0 for t in out):
        raise ValueError(
            f"thickness must be a compressed thickness in mm (> 0) or a non-empty list of them, "
            f"got {setting!r}"
        )
    return out


def set_laterality(traj: Trajectory, setting: str | None) -> None:
    """Record the ``laterality`` setting in ``traj``; without one, the file must record it.

    Raises
    ------
    ValueError
        No laterality in the setting nor in the file; the message names the file and the
        setting.
    """
    if setting is not None:
        traj.metadata["laterality"] = setting
    elif traj.metadata.get("laterality") not in LATERALITIES:
        raise ValueError(
            f"{traj.source}: metadata field 'laterality' must be 'L' or 'R', got "
            f"{traj.metadata.get('laterality')!r}: set laterality=L or laterality=R"
        )


def predict(cfg: DictConfig) -> Path:
    """Run the command on a composed config; returns the output folder.

    Every input is read and checked, and the shapes predicted and checked (`checks`), before
    the first file is written."""
    out = Path(cfg.out_dir)
    writable_folder(out)
    checks = instantiate(cfg.checks)
    thickness = thicknesses(cfg.thickness)
    if cfg.laterality not in (None, *LATERALITIES):
        raise ValueError(f"laterality must be L, R or null (the file's), got {cfg.laterality!r}")
    source = Path(to_absolute_path(cfg.input))
    traj = instantiate(cfg.reader)(source)
    set_laterality(traj, cfg.laterality)
    unloaded, compression = (
        load_surrogate(to_absolute_path(path), step, precision=cfg.precision)
        for path, step in ((cfg.unloaded_model, "unloaded"), (cfg.compression_model, "compression"))
    )
    landmarks = Path(to_absolute_path(cfg.landmarks)) if cfg.landmarks else None
    names, points = read_landmarks(landmarks) if landmarks else ([], None)
    start = time.perf_counter()
    shapes = predict_breast(traj, unloaded, compression, thickness)
    seconds = time.perf_counter() - start
    record = checks(traj, shapes)
    rows = landmarks and map_landmarks(
        traj, shapes, names, points, cfg.source_to_image_mm, str(landmarks)
    )
    input_format = file_suffix(source) if file_kind(source) == "mesh" else None
    written = write_shapes(traj, shapes, out, input_format)
    written.append(write_json({"seconds": seconds, "checks": record}, out / "checks.json"))
    if cfg.figures:
        for k, t in enumerate(shapes.thickness):
            shapes_k = {
                "imaged": traj.points,
                f"unloaded ({unloaded.name})": shapes.unloaded[-1],
                f"compressed to {t:g} mm ({compression.name})": shapes.compressed[k, -1],
            }
            title = f"{source.name}: predicted shapes, {t:g} mm"
            written.append(
                shapes_sections_png(
                    traj.cells, traj.tissue, shapes_k, title, out / f"preview_{t:g}mm.png"
                )
            )
    if rows:
        written.append(write_rows(rows, out / "landmarks.csv"))
    print(
        f"{traj.n_nodes} nodes, {len(thickness)} thickness(es): predicted in {1e3 * seconds:.0f} ms"
    )
    print("\n".join(f"wrote {p}" for p in written))
    return out


@hydra.main(config_path="conf", config_name="predict", version_base="1.3")
def main(cfg: DictConfig) -> None:
    predict(cfg)


if __name__ == "__main__":
    main()
