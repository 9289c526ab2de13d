"""A real image's way, with documented settings only: a breast-CT-style segmentation (labels
background 0, fat 1, gland 2, skin 3; no muscle, cropped at the chest; its third array axis
running from the nipple to the chest wall) through fem.mesh_breast, fem.simulate and predict.py."""

from __future__ import annotations

import json

import meshio
import nrrd
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from test_predictor import models  # noqa: F401  (fixture: a tiny network and XGBoost)

import predict
from fem import CONFIG_DIR
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Trajectory
from fem.engine.boundary import chest_wall_nodes
from fem.mesh_breast import mesh_breast
from fem.simulate import simulate_file

#: How the image is read: its labels and the direction each array axis grows (the header is
#: identity, as many breast-CT files are).
SETTINGS = (
    "reader.label_map.skin=3",
    "reader.label_map.muscle=[]",
    "reader.orientation=RSP",
)


def breast_ct(path):
    """A half-ellipsoid breast (fat, a gland core, a 2 mm skin shell) in front of a flat chest
    cut, written as NRRD with the axes (right, superior, posterior), 1 mm voxels."""
    x, y, z = np.meshgrid(
        np.arange(-48, 49), np.arange(0, 56), np.arange(-42, 43), indexing="ij"
    )  # RAS+, mm; y = 0 is the chest-wall cut
    r = np.sqrt((x / 44.0) ** 2 + (y / 48.0) ** 2 + (z / 38.0) ** 2)
    labels = np.zeros(x.shape, np.uint8)
    labels[r <= 1] = 3  # skin
    labels[r <= 1 - 2.0 / 40] = 1  # fat
    labels[(x / 16.0) ** 2 + ((y - 18) / 14.0) ** 2 + (z / 14.0) ** 2 <= 1] = 2  # gland
    rsp = labels.transpose(0, 2, 1)[:, :, ::-1]  # axis 2 from the nipple to the chest
    nrrd.write(str(path), np.ascontiguousarray(rsp), {"space": "right-anterior-superior"})
    return labels


def _compose(name, *overrides):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(name, overrides=[*SETTINGS, *overrides])


def test_muscle_less_breast_ct_meshes_simulates_and_predicts(tmp_path, models):  # noqa: F811
    image = tmp_path / "case01.nrrd"
    labels = breast_ct(image)
    # 1. fem.mesh_breast: anterior is +y, the cut face is the chest wall, the skin label is breast
    stem = mesh_breast(_compose("mesh_breast", f"input={image}", f"output={tmp_path / 'mesh'}"))
    mesh = Trajectory.load(stem.with_suffix(".npz"))
    assert (stem.with_suffix(".png")).exists() and (stem.with_suffix(".vtu")).exists()
    y = mesh.points[:, 1]
    chest = chest_wall_nodes(mesh)
    assert np.ptp(y) == pytest.approx(48, abs=4)  # the breast's depth, along the image's axis 2
    assert y[chest].max() - y.min() < 5 and chest.size > 20  # held at the posterior cut
    assert mesh.points[:, 1].mean() > y.min() + 10  # tissue lies anterior of the chest
    volume = signed_volume(mesh.points, mesh.cells).sum() / 1e3
    assert volume == pytest.approx((labels > 0).sum() / 1e3, rel=0.05)  # skin voxels included
    # 2. fem.simulate on the image itself, both steps
    cfg = _compose(
        "simulate", f"input={image}", f"output={tmp_path / 'fe'}", "time_series=false",
        "simulation.compression_ratio=0.3", "simulation.unloaded_steps=3",
        "simulation.compression_steps=4",
    )  # fmt: skip
    fe = Trajectory.load(simulate_file(cfg).with_suffix(".npz"))
    assert fe.compression_ratio[-1] == pytest.approx(0.3)
    held = np.setdiff1d(chest_wall_nodes(fe), fe.flagged(NodeFlag.SKIN))  # the rim slides
    np.testing.assert_array_equal(fe.unloaded[-1][held], fe.points[held])
    assert fe.metadata["simulation"]["min_element_volume_ratio"] > 0
    # 3. predict.py on the image itself
    thickness = 0.7 * np.ptp(fe.unloaded[-1][:, 2])
    cfg = _compose(
        "predict", f"input={image}", f"thickness={thickness:.1f}", "laterality=L",
        f"unloaded_model={models / 'unloaded.ckpt'}",
        f"compression_model={models / 'compression.json'}", f"out_dir={tmp_path / 'pred'}",
    )  # fmt: skip
    out = predict.predict(cfg)
    final = meshio.read(out / f"compressed_{float(f'{thickness:.1f}'):g}mm.vtu")
    assert final.points.shape == mesh.points.shape
    checks = json.loads((out / "checks.json").read_text())["checks"]
    assert set(checks["shapes"]) == {"unloaded", f"compressed_{float(f'{thickness:.1f}'):g}mm"}
