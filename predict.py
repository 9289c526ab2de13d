"""Deformed meshes of a new breast from the trained surrogates, in milliseconds, without FE.

    python predict.py input=case01.vtu thickness=55 laterality=L \
        unloaded_model=<run>/checkpoints/last.ckpt compression_model=<run>/baselines/xgboost.json \
        [landmarks=lesions.csv] [out_dir=outputs/predict/case01] [reader.label_map.gland=[2,4]]

The input (a Trajectory, a tetrahedral mesh or a segmentation, meshed first), read by the
``reader`` group (`fem.breasts.io.BreastReader`), goes through the unloaded-state model, then
the compression model for each thickness (`mammo_net.predictor`).
Writes the final shapes (VTU, and the input's format where meshio writes it), every step as an
XDMF time series, a PNG preview in three body planes, the mapped landmarks (CSV, mm) and
``checks.json``: the prediction time, what the projection onto valid shapes moved
(``projection``, on by default; ``projection=raw`` writes the raw predictions) and the physical
checks of every shape (`mammo_net.validity`: inverted elements, volume change, skin inside a
plate), which also warn, or refuse the output with ``checks.on_violation=refuse``.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig

from fem.breasts.io import file_kind, file_suffix
from fem.contract.atomic import writable_folder, write_json
from mammo_net.predictor import (
    check_laterality,
    load_surrogate,
    map_landmarks,
    predict_breast,
    read_landmarks,
    set_laterality,
    thicknesses,
    write_previews,
    write_rows,
    write_shapes,
)


def predict(cfg: DictConfig) -> Path:
    """Run the command on a composed config; returns the output folder.

    Every input is read and checked, and the shapes predicted and checked (`checks`), before
    the first file is written."""
    out = Path(cfg.out_dir)
    writable_folder(out)
    checks = instantiate(cfg.checks)
    thickness = thicknesses(cfg.thickness)
    check_laterality(cfg.laterality)
    conditions = instantiate(cfg.conditions)
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
    shapes = predict_breast(traj, unloaded, compression, thickness, conditions)
    seconds = time.perf_counter() - start
    projected = None
    if cfg.get("projection"):  # onto physically valid shapes before they are checked
        shapes, projected = instantiate(cfg.projection)(traj, shapes)
    record = {**checks(traj, shapes), "projection": projected}
    rows = landmarks and map_landmarks(
        traj, shapes, names, points, cfg.source_to_image_mm, str(landmarks)
    )
    input_format = file_suffix(source) if file_kind(source) == "mesh" else None
    written = write_shapes(traj, shapes, out, input_format)
    written.append(write_json({"seconds": seconds, "checks": record}, out / "checks.json"))
    if cfg.figures:
        names = (unloaded.name, compression.name)
        written += write_previews(traj, shapes, names, source.name, out)
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
