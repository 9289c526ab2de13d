"""Mesh one user breast from a segmentation or read their tetrahedral mesh.

    python -m fem.mesh_breast input=case01.nii.gz reader.label_map.gland=[2,4] output=out/case01

The input is read by the ``reader`` group (`fem.breasts.io.BreastReader`; options
``reader.label_map``, ``reader.spacing``, ``reader.units``, ``reader.orientation``,
``reader.extent_mm``, ``reader.tissue_field``, ``reader.mesher.*``), which checks every
setting and the file before any output is written: a bad input leaves no file. Writes
``<output>.vtu`` (ParaView, tissue fields), ``<output>.npz`` (the `Trajectory`) and, with
``figures=true``, ``<output>.png`` (body-plane sections, axes labelled with the body
directions), each atomically. A mesh whose volume misses the segmentation's by more than 5 %
is written with a warning (`fem.breasts.io.warn_volume_error`).

    python -m fem.mesh_breast input=ct.nrrd reader.orientation=RSA reader.label_map.skin=3 \
        reader.label_map.muscle=[]
"""

from __future__ import annotations

import json
from pathlib import Path

import hydra
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig

from fem import CONFIG_DIR
from fem.breasts.figures import breast_sections_png
from fem.breasts.io import write_mesh


def mesh_breast(cfg: DictConfig) -> Path:
    """Run the command on a composed config; returns the output stem."""
    source = Path(to_absolute_path(cfg.input))
    stem = (
        Path(to_absolute_path(cfg.output))
        if cfg.output
        else source.with_name(source.name.split(".")[0])
    )
    traj, volume = instantiate(cfg.reader).read(source)
    write_mesh(traj, stem.with_suffix(".vtu"))
    if cfg.figures:
        breast_sections_png(traj, stem.with_suffix(".png"), volume)
    traj.save(stem.with_suffix(".npz"))
    print(json.dumps(traj.metadata.get("mesh", {"n_elements": traj.n_cells}), indent=2))
    print(f"wrote {stem}.vtu, {stem}.npz" + (f", {stem}.png" if cfg.figures else ""))
    return stem


@hydra.main(config_path=CONFIG_DIR, config_name="mesh_breast", version_base="1.3")
def main(cfg: DictConfig) -> None:
    mesh_breast(cfg)


if __name__ == "__main__":
    main()
