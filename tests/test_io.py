from dataclasses import replace
from pathlib import Path

import meshio
import nibabel
import nrrd
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from scipy import ndimage

from fem.breasts.figures import AXIS_NAMES
from fem.breasts.io import (
    BreastReader,
    file_kind,
    orientation_matrix,
    read_mesh,
    read_segmentation,
    write_mesh,
)
from fem.breasts.mesh import Mesher
from fem.contract.trajectory import Tissue, Trajectory

CONF = str(Path(__file__).resolve().parents[1] / "conf")

USER_LABELS = {"background": 0, "fat": 10, "gland": [20, 21], "muscle": 30}


def _user_labels(volume):
    """The ellipsoid phantom relabelled with a user's label values."""
    out = np.zeros(volume.labels.shape, np.int16)
    out[volume.labels == Tissue.FAT] = 10
    out[volume.labels == Tissue.GLAND] = 21
    out[volume.labels == Tissue.MUSCLE] = 30
    return out


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd", ".npy", ".npz"])
def test_user_segmentation_meshes(tmp_path, ellipsoid_volume, suffix):
    data = _user_labels(ellipsoid_volume)
    path = tmp_path / f"seg{suffix}"
    if suffix == ".nii.gz":
        nibabel.save(nibabel.Nifti1Image(data, ellipsoid_volume.affine), str(path))
    elif suffix == ".nrrd":  # LPS space, as 3D Slicer writes
        header = {
            "space": "left-posterior-superior",
            "space directions": np.diag([-1.0, -1.0, 1.0]),
            "space origin": -ellipsoid_volume.affine[:3, 3] * [1, 1, -1],
        }
        nrrd.write(str(path), data, header)
    elif suffix == ".npy":
        np.save(path, data)
    else:
        np.savez(path, labels=data, affine=ellipsoid_volume.affine)
    volume = read_segmentation(path, USER_LABELS)
    np.testing.assert_array_equal(volume.labels, ellipsoid_volume.labels)
    if suffix != ".npy":
        np.testing.assert_allclose(volume.affine, ellipsoid_volume.affine)
    reader = BreastReader(USER_LABELS, mesher=Mesher(target_elements=900, tolerance=150))
    mesh, read_volume = reader.read(path)
    assert 750 <= mesh.n_cells <= 1050
    assert set(np.unique(mesh.tissue)) == {1, 2, 3}
    np.testing.assert_array_equal(read_volume.labels, ellipsoid_volume.labels)
    assert mesh.metadata["source"] == str(path) and file_kind(path) == "segmentation"


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.nii\.gz"):
        read_segmentation(tmp_path / "nope.nii.gz")
    with pytest.raises(FileNotFoundError, match=r"nope\.vtu"):
        BreastReader()(tmp_path / "nope.vtu")


def test_unknown_label_value(tmp_path, ellipsoid_volume):
    data = _user_labels(ellipsoid_volume)
    data[0, 0, 0] = 99
    np.save(tmp_path / "seg.npy", data)
    with pytest.raises(ValueError, match=r"seg\.npy: field 'labels' contains value\(s\) \[99\]"):
        read_segmentation(tmp_path / "seg.npy", USER_LABELS)


def test_no_breast_labels(tmp_path):
    data = np.zeros((10, 10, 10), np.uint8)
    data[2:5, 2:5, 2:5] = 3
    np.save(tmp_path / "muscle_only.npy", data)
    with pytest.raises(ValueError, match=r"muscle_only\.npy: no breast labels"):
        read_segmentation(tmp_path / "muscle_only.npy")


@pytest.mark.parametrize(
    ("suffix", "field", "fmt"),
    [
        (".vtu", "tissue", None),
        (".vtk", "tissue", None),
        (".msh", "gmsh:physical", "gmsh22"),
        (".mesh", "medit:ref", None),
    ],
)
def test_meshio_round_trip(tmp_path, breast_mesh, suffix, field, fmt):
    path = tmp_path / f"breast{suffix}"
    if field == "tissue":
        write_mesh(breast_mesh, path)
    else:  # Gmsh physical groups / MEDIT references carry the tissue
        tissue = [breast_mesh.tissue.astype(np.int32)]
        data = {field: tissue, **({"gmsh:geometrical": tissue} if fmt else {})}
        meshio.write(
            path,
            meshio.Mesh(breast_mesh.points, [("tetra", breast_mesh.cells)], cell_data=data),
            file_format=fmt,
        )
    back = read_mesh(path, tissue_field=field)
    np.testing.assert_allclose(back.points, breast_mesh.points)
    np.testing.assert_array_equal(back.cells, breast_mesh.cells)
    np.testing.assert_array_equal(back.tissue, breast_mesh.tissue)
    np.testing.assert_array_equal(back.node_tissue_code, breast_mesh.node_tissue_code)
    np.testing.assert_array_equal(back.node_flags, breast_mesh.node_flags)
    np.testing.assert_array_equal(back.skin, breast_mesh.skin)


def test_abaqus_element_sets(tmp_path, breast_mesh):
    sets = {
        name.upper(): [np.flatnonzero(breast_mesh.tissue == t)]
        for name, t in (("fat", 1), ("gland", 2), ("muscle", 3))
    }
    m = meshio.Mesh(breast_mesh.points, [("tetra", breast_mesh.cells)], cell_sets=sets)
    meshio.write(tmp_path / "breast.inp", m)
    back = read_mesh(tmp_path / "breast.inp")
    np.testing.assert_array_equal(back.tissue, breast_mesh.tissue)


def test_mesh_without_tetrahedra(tmp_path):
    m = meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))])
    meshio.write(tmp_path / "surface.vtu", m)
    with pytest.raises(ValueError, match=r"surface\.vtu: no tetrahedral cells \(found: triangle\)"):
        read_mesh(tmp_path / "surface.vtu")


def test_mesh_with_inverted_tetrahedron(tmp_path, breast_mesh):
    cells = breast_mesh.cells.copy()
    cells[5] = cells[5][[0, 2, 1, 3]]
    m = meshio.Mesh(
        breast_mesh.points, [("tetra", cells)], cell_data={"tissue": [breast_mesh.tissue]}
    )
    meshio.write(tmp_path / "bad.vtu", m)
    with pytest.raises(ValueError, match=r"bad\.vtu: 1 inverted tetrahedra.*\[5\]"):
        read_mesh(tmp_path / "bad.vtu")


def test_consistently_reversed_mesh_is_reoriented(tmp_path, breast_mesh):
    m = meshio.Mesh(
        breast_mesh.points,
        [("tetra", breast_mesh.cells[:, [1, 0, 2, 3]])],
        cell_data={"tissue": [breast_mesh.tissue]},
    )
    meshio.write(tmp_path / "rev.vtu", m)
    assert read_mesh(tmp_path / "rev.vtu").n_cells == breast_mesh.n_cells


def test_mesh_without_tissue(tmp_path, breast_mesh):
    meshio.write(
        tmp_path / "plain.vtu", meshio.Mesh(breast_mesh.points, [("tetra", breast_mesh.cells)])
    )
    with pytest.raises(
        ValueError, match=r"plain\.vtu: no per-cell tissue: cell field 'tissue' is missing"
    ):
        read_mesh(tmp_path / "plain.vtu")


def test_unknown_tissue_value_in_mesh(tmp_path, breast_mesh):
    tissue = breast_mesh.tissue.astype(int)
    tissue[3] = 9
    m = meshio.Mesh(
        breast_mesh.points, [("tetra", breast_mesh.cells)], cell_data={"tissue": [tissue]}
    )
    meshio.write(tmp_path / "t.vtu", m)
    with pytest.raises(ValueError, match=r"t\.vtu: cell field 'tissue' contains value\(s\) \[9\]"):
        read_mesh(tmp_path / "t.vtu")


def test_trajectory_round_trip(tmp_path, breast_mesh):
    path = breast_mesh.save(tmp_path / "b.npz")
    back = Trajectory.load(path)
    for name in (
        "points",
        "cells",
        "tissue",
        "node_tissue_code",
        "node_flags",
        "skin",
        "unloaded",
        "compressed",
        "plates",
        "compression_ratio",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(breast_mesh, name))
    assert back.metadata == breast_mesh.metadata
    assert BreastReader()(path).n_cells == breast_mesh.n_cells
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind


def test_trajectory_rejects_bad_fields(tmp_path, breast_mesh):
    with pytest.raises(ValueError, match="field 'tissue' has shape"):
        Trajectory(
            breast_mesh.points,
            breast_mesh.cells,
            breast_mesh.tissue[:-1],
            breast_mesh.node_tissue_code,
            breast_mesh.node_flags,
            breast_mesh.skin,
        )
    pts = breast_mesh.points.copy()
    pts[0, 0] = np.nan
    with pytest.raises(ValueError, match="field 'points' contains NaN"):
        Trajectory(
            pts,
            breast_mesh.cells,
            breast_mesh.tissue,
            breast_mesh.node_tissue_code,
            breast_mesh.node_flags,
            breast_mesh.skin,
        )
    np.savez(tmp_path / "old.npz", schema_version=0)
    with pytest.raises(ValueError, match=r"old\.npz: field 'schema_version' is 0"):
        Trajectory.load(tmp_path / "old.npz")


def test_reader_uses_meshes_and_trajectories_as_is(tmp_path, breast_mesh):
    reader = BreastReader(tissue_field="medit:ref", mesher=Mesher(tolerance=0, max_attempts=1))
    mesh_file = tmp_path / "breast.mesh"
    tissue = {"medit:ref": [breast_mesh.tissue.astype(np.int32)]}
    meshio.write(
        mesh_file, meshio.Mesh(breast_mesh.points, [("tetra", breast_mesh.cells)], cell_data=tissue)
    )
    traj_file = breast_mesh.save(tmp_path / "breast.npz")
    named = replace(breast_mesh, metadata={**breast_mesh.metadata, "source": "P0001_L"})
    named_file = named.save(tmp_path / "named.npz")
    sources = {mesh_file: str(mesh_file), traj_file: str(traj_file), named_file: "P0001_L"}
    for path, source in sources.items():
        traj, volume = reader.read(path)  # its mesher, which would fail, is not called
        assert volume is None
        np.testing.assert_array_equal(traj.cells, breast_mesh.cells)
        np.testing.assert_array_equal(traj.tissue, breast_mesh.tissue)
        assert traj.metadata["source"] == source
    assert [file_kind(p) for p in (mesh_file, traj_file)] == ["mesh", "trajectory"]


@pytest.mark.parametrize("command", ["predict", "simulate", "mesh_breast"])
def test_commands_share_the_reader_group(command):
    overrides = ["reader.label_map.gland=[2,4]", "reader.mesher.target_elements=900"]
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(command, overrides=overrides)
    assert not {"label_map", "spacing", "tissue_field", "mesher"} & set(cfg)
    expected = BreastReader(
        {"background": 0, "fat": 1, "gland": [2, 4], "muscle": 3, "skin": []},
        [1.0, 1.0, 1.0],
        "tissue",
        Mesher(target_elements=900),
        extent_mm=[20.0, 500.0],
    )
    assert instantiate(cfg.reader) == expected


# --- units, orientation, skin, the volume warning ---------------------------------------------


@pytest.mark.parametrize(("units", "factor"), [("m", 1e-3), ("cm", 0.1)])
def test_a_mesh_in_other_units_is_read_in_mm(tmp_path, breast_mesh, units, factor):
    m = meshio.Mesh(
        breast_mesh.points * factor,
        [("tetra", breast_mesh.cells)],
        cell_data={"tissue": [breast_mesh.tissue]},
    )
    meshio.write(tmp_path / "breast.vtu", m)
    back = BreastReader(units=units)(tmp_path / "breast.vtu")
    np.testing.assert_allclose(back.points, breast_mesh.points, rtol=1e-12)
    np.testing.assert_array_equal(back.node_flags, breast_mesh.node_flags)


def test_a_segmentation_in_metres_is_read_in_mm(tmp_path, ellipsoid_volume):
    affine = ellipsoid_volume.affine.copy()
    affine[:3] *= 1e-3
    nibabel.save(nibabel.Nifti1Image(ellipsoid_volume.labels, affine), str(tmp_path / "m.nii"))
    volume = read_segmentation(tmp_path / "m.nii", units="m")
    np.testing.assert_allclose(volume.affine, ellipsoid_volume.affine, atol=1e-12)


def _breast_axes(volume):
    """Mean RAS+ position of the fat and of the muscle voxels, mm."""
    ijk = {t: np.argwhere(volume.labels == t) for t in (Tissue.FAT, Tissue.MUSCLE)}
    return {t: (v @ volume.affine[:3, :3].T + volume.affine[:3, 3]).mean(0) for t, v in ijk.items()}


@pytest.mark.parametrize(("code", "flip"), [("RSA", False), ("RSP", True)])
def test_orientation_setting_turns_a_breast_ct_volume(tmp_path, ellipsoid_volume, code, flip):
    """A breast-CT-style array whose third axis runs front-wards ("RSA") or back-wards ("RSP"),
    in an NRRD whose header claims plain RAS axes: only reader.orientation makes it right."""
    data = ellipsoid_volume.labels.transpose(0, 2, 1)  # axes: right, superior, anterior
    data = data[:, :, ::-1] if flip else data
    nrrd.write(str(tmp_path / "ct.nrrd"), np.ascontiguousarray(data), {"space": "RAS"})
    trusted = _breast_axes(read_segmentation(tmp_path / "ct.nrrd"))
    assert trusted[Tissue.FAT][1] == pytest.approx(trusted[Tissue.MUSCLE][1], abs=1)  # y lost
    volume = read_segmentation(tmp_path / "ct.nrrd", orientation=code)
    centre = _breast_axes(volume)
    assert centre[Tissue.FAT][1] > centre[Tissue.MUSCLE][1] + 15  # anterior is +y
    np.testing.assert_array_equal(volume.labels, ellipsoid_volume.labels)  # RAS axis order
    np.testing.assert_allclose(volume.affine[:3, :3], np.eye(3))


def test_orientation_of_a_mesh_and_the_codes(tmp_path, breast_mesh):
    np.testing.assert_array_equal(orientation_matrix("LPS"), np.diag([-1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(orientation_matrix("ras"), np.eye(3))
    m = meshio.Mesh(
        breast_mesh.points * [-1, 1, 1],  # x grows to the left: a mirror
        [("tetra", breast_mesh.cells)],
        cell_data={"tissue": [breast_mesh.tissue]},
    )
    meshio.write(tmp_path / "las.vtu", m)
    back = read_mesh(tmp_path / "las.vtu", orientation="LAS")
    np.testing.assert_allclose(back.points, breast_mesh.points)
    np.testing.assert_array_equal(back.skin.shape, breast_mesh.skin.shape)


def test_the_sections_name_the_body_directions():
    assert [name.split()[-1] for name in AXIS_NAMES] == ["right", "anterior", "superior"]


def test_a_skin_label_is_breast(tmp_path, ellipsoid_volume):
    """The image's skin (value 3 here, muscle 4) is meshed as fat, under the skin membrane."""
    labels = ellipsoid_volume.labels
    breast = np.isin(labels, (Tissue.FAT, Tissue.GLAND))
    skin = breast & ~ndimage.binary_erosion(breast)
    data = np.where(labels == Tissue.MUSCLE, 4, labels).astype(np.int16)
    data[skin] = 3
    np.save(tmp_path / "skin.npy", data)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "mesh_breast",
            overrides=[
                f"input={tmp_path / 'skin.npy'}",
                "reader.label_map.skin=3",
                "reader.label_map.muscle=4",
                "reader.mesher.target_elements=900",
                "reader.mesher.tolerance=150",
            ],
        )
    mesh, volume = instantiate(cfg.reader).read(tmp_path / "skin.npy")
    np.testing.assert_array_equal(volume.labels, labels)
    assert set(np.unique(mesh.tissue)) == {1, 2, 3}


def test_a_coarse_mesh_warns_of_its_volume_error(tmp_path, ellipsoid_volume, recwarn):
    np.save(tmp_path / "seg.npy", ellipsoid_volume.labels)
    BreastReader(mesher=Mesher(target_elements=900, tolerance=150))(tmp_path / "seg.npy")
    assert not recwarn.list  # a mesh within 5 % of the segmentation's volume
    coarse = BreastReader(mesher=Mesher(target_elements=200, tolerance=100))
    with pytest.warns(UserWarning, match=r"seg\.npy: the mesh's volume .* misses") as info:
        traj = coarse(tmp_path / "seg.npy")
    error = traj.metadata["mesh"]["volume_error"]
    assert abs(error) > 0.05 and f"{100 * error:+.1f} %" in str(info[0].message)
    assert "reader.mesher.target_elements (now 200)" in str(info[0].message)
