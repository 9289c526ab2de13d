"""Reading a user's breast (segmentation or tetrahedral mesh) and writing meshes.

Segmentations: NIfTI (``.nii``, ``.nii.gz``, read with nibabel, affine in RAS+ mm), NRRD
(``.nrrd``, ``.nhdr``, read with pynrrd, its ``space`` converted to RAS+), NumPy (``.npy``
array, or ``.npz`` with ``labels`` and optional ``affine``/``spacing``; axes taken as RAS+).
A label map (tissue name -> file values) turns the file's values into `Tissue` labels.

Meshes: anything meshio reads (ABAQUS ``.inp``, VTK/VTU, Gmsh ``.msh``, MEDIT ``.mesh``...)
with tetrahedra and a per-cell tissue array (a cell-data field, or for ABAQUS element sets
named after the tissues), used as is.

`BreastReader` reads any of them, and saved `Trajectory` files, the same way for every command.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import meshio
import numpy as np
from numpy.typing import NDArray

from fem.breasts.mesh import Mesher, annotate
from fem.breasts.phantom import LabelVolume
from fem.contract.atomic import atomic_path
from fem.contract.quality import signed_volume
from fem.contract.trajectory import Tissue, Trajectory

SEGMENTATION_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy", ".npz")

#: Default label map: the canonical `Tissue` values.
DEFAULT_LABELS: dict[str, int | list[int]] = {"background": 0, "fat": 1, "gland": 2, "muscle": 3}


def file_suffix(path: Path) -> str:
    """The lower-case suffix of ``path``, ``.nii.gz`` counted as one."""
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _require_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return path


def _nrrd_affine(header: Mapping, path: Path) -> NDArray[np.float64]:
    directions = np.asarray(header.get("space directions", np.eye(3)), float)
    if directions.shape != (3, 3) or not np.isfinite(directions).all():
        raise ValueError(
            f"{path}: field 'space directions' must be a 3x3 matrix for a 3-D label volume"
        )
    origin = np.asarray(header.get("space origin", np.zeros(3)), float)
    space = str(header.get("space", "right-anterior-superior")).lower()
    flip = {
        "right-anterior-superior": [1, 1, 1],
        "ras": [1, 1, 1],
        "left-posterior-superior": [-1, -1, 1],
        "lps": [-1, -1, 1],
        "left-anterior-superior": [-1, 1, 1],
        "las": [-1, 1, 1],
    }
    if space not in flip:
        raise ValueError(f"{path}: field 'space' is {space!r}; supported: {sorted(flip)}")
    affine = np.eye(4)
    affine[:3, :3] = np.diag(flip[space]) @ directions.T  # columns: world step per index
    affine[:3, 3] = np.asarray(flip[space]) * origin
    return affine


def read_segmentation(
    path: str | Path,
    label_map: Mapping[str, int | Sequence[int]] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
) -> LabelVolume:
    """Read a labelled breast segmentation as canonical `Tissue` labels.

    Parameters
    ----------
    path : str or Path
        NIfTI, NRRD or NumPy file.
    label_map : mapping, optional
        Tissue name (``background``, ``fat``, ``gland``, ``muscle``) -> value or list of values
        in the file. Defaults to `DEFAULT_LABELS`.
    spacing : (3,) float
        Voxel size in mm for NumPy arrays without an affine.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        The array is not 3-D, holds values missing from the label map, or has no fat or gland.
    """
    path = _require_file(path)
    suffix = file_suffix(path)
    if suffix in (".nii", ".nii.gz"):
        import nibabel

        img = nibabel.load(str(path))
        data, affine = np.asanyarray(img.dataobj), np.asarray(img.affine, float)
    elif suffix in (".nrrd", ".nhdr"):
        import nrrd

        data, header = nrrd.read(str(path))
        affine = _nrrd_affine(header, path)
    elif suffix == ".npy":
        data, affine = np.load(path, allow_pickle=False), np.diag([*spacing, 1.0])
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if "labels" not in z:
                raise ValueError(f"{path}: field 'labels' is missing (found {sorted(z.files)})")
            data = z["labels"]
            if "affine" in z:
                affine = np.asarray(z["affine"], float)
            else:
                affine = np.diag([*(z["spacing"] if "spacing" in z else spacing), 1.0])
    else:
        raise ValueError(
            f"{path}: unknown segmentation format; expected one of {SEGMENTATION_SUFFIXES}"
        )
    data = np.asarray(data)
    if data.ndim != 3:
        raise ValueError(f"{path}: field 'labels' must be a 3-D array, got shape {data.shape}")
    if not np.issubdtype(data.dtype, np.integer):
        if not np.all(np.mod(data, 1) == 0):
            raise ValueError(f"{path}: field 'labels' holds non-integer values ({data.dtype})")
        data = data.astype(np.int64)
    label_map = dict(DEFAULT_LABELS if label_map is None else label_map)
    lut: dict[int, Tissue] = {}
    for name, values in label_map.items():
        try:
            tissue = Tissue[name.upper()]
        except KeyError:
            raise ValueError(
                f"label map for {path}: unknown tissue {name!r}; use background, fat, gland, muscle"
            ) from None
        for v in np.atleast_1d(values):
            lut[int(v)] = tissue
    values = np.unique(data)
    unknown = [int(v) for v in values if int(v) not in lut]
    if unknown:
        raise ValueError(
            f"{path}: field 'labels' contains value(s) {unknown} that are not in the label map {label_map}"
        )
    labels = np.zeros(data.shape, np.uint8)
    for v in values:
        labels[data == v] = lut[int(v)]
    if not np.isin(labels, (Tissue.FAT, Tissue.GLAND)).any():
        raise ValueError(
            f"{path}: no breast labels (fat or gland) in field 'labels' with label map {label_map}"
        )
    return LabelVolume(labels, affine, str(path))


def read_mesh(
    path: str | Path,
    tissue_field: str = "tissue",
    tissue_values: Mapping[str, int | Sequence[int]] | None = None,
) -> Trajectory:
    """Read a tetrahedral breast mesh (any meshio format) with a per-cell tissue array.

    Parameters
    ----------
    path : str or Path
        Mesh file.
    tissue_field : str
        Cell-data array holding the tissue of each tetrahedron. For files without it (e.g.
        ABAQUS ``.inp``), element sets named ``fat``, ``gland``, ``muscle`` (any case) are used.
    tissue_values : mapping, optional
        Tissue name -> value(s) in ``tissue_field``; defaults to the canonical labels.

    A mesh whose tetrahedra are all negatively oriented (a convention of some writers) is
    reoriented; a mesh with a mix of orientations, or flat elements, is refused.
    """
    path = _require_file(path)
    try:
        mesh = meshio.read(path)
    except Exception as exc:  # meshio raises many types; name the file in one message
        raise ValueError(f"{path}: meshio could not read it ({exc})") from exc
    blocks = [i for i, c in enumerate(mesh.cells) if c.type == "tetra"]
    if not blocks:
        found = sorted({c.type for c in mesh.cells}) or ["no cells"]
        raise ValueError(f"{path}: no tetrahedral cells (found: {', '.join(found)})")
    cells = np.vstack([mesh.cells[i].data for i in blocks]).astype(np.int64)
    values = dict(DEFAULT_LABELS if tissue_values is None else tissue_values)
    values.pop("background", None)
    if tissue_field in mesh.cell_data:
        raw = np.concatenate([np.asarray(mesh.cell_data[tissue_field][i]).ravel() for i in blocks])
        tissue = np.zeros(len(raw), np.uint8)
        for name, vals in values.items():
            tissue[np.isin(raw, np.atleast_1d(vals))] = Tissue[name.upper()]
        unknown = np.unique(raw[tissue == 0])
        if unknown.size:
            raise ValueError(
                f"{path}: cell field '{tissue_field}' contains value(s) {unknown.tolist()} "
                f"that are not in the tissue map {values}"
            )
    else:
        tissue = _tissue_from_sets(mesh, blocks, path, tissue_field)
    points = np.asarray(mesh.points, float)
    if points.shape[1] != 3:
        raise ValueError(f"{path}: field 'points' must be 3-D, got {points.shape[1]} coordinates")
    vol = signed_volume(points, cells)
    if (vol < 0).all():
        cells = cells[:, [0, 2, 1, 3]]
    elif (vol < 0).any():
        bad = (
            np.flatnonzero(vol < 0)
            if (vol > 0).sum() > (vol < 0).sum()
            else np.flatnonzero(vol > 0)
        )
        raise ValueError(
            f"{path}: {bad.size} inverted tetrahedra (orientation opposite to the rest), "
            f"first cells {bad[:5].tolist()}"
        )
    return annotate(points, cells, tissue, {"source": str(path)}, source=str(path))


def _tissue_from_sets(
    mesh: meshio.Mesh, blocks: list[int], path: Path, field: str
) -> NDArray[np.uint8]:
    sizes = [len(mesh.cells[i].data) for i in blocks]
    tissue = np.zeros(sum(sizes), np.uint8)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    for name, per_block in mesh.cell_sets.items():
        key = name.strip().upper()
        if key not in ("FAT", "GLAND", "MUSCLE"):
            continue
        for k, i in enumerate(blocks):
            idx = np.asarray(per_block[i]) if i < len(per_block) else np.zeros(0, int)
            tissue[offsets[k] + idx.astype(int)] = Tissue[key]
    if (tissue == 0).all():
        raise ValueError(
            f"{path}: no per-cell tissue: cell field '{field}' is missing "
            f"(cell fields: {sorted(mesh.cell_data)}) and no element sets are named fat/gland/muscle "
            f"(sets: {sorted(mesh.cell_sets)})"
        )
    if (tissue == 0).any():
        raise ValueError(
            f"{path}: {(tissue == 0).sum()} tetrahedra belong to no fat/gland/muscle element set"
        )
    return tissue


def file_kind(path: str | Path) -> Literal["segmentation", "trajectory", "mesh"]:
    """What a breast file holds, judged by its suffix (for ``.npz``, by its fields).

    Returns
    -------
    {"segmentation", "trajectory", "mesh"}
        A label volume (to be meshed), a saved `Trajectory` (``.npz`` with a
        ``schema_version``) or a tetrahedral mesh (any other suffix, read by meshio).
    """
    path = Path(path)
    if file_suffix(path) == ".npz" and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return "trajectory" if "schema_version" in z else "segmentation"
    return "segmentation" if file_suffix(path) in SEGMENTATION_SUFFIXES else "mesh"


@dataclass(frozen=True)
class BreastReader:
    """A user's breast file -> mesh-only `Trajectory`: the input loader of every command.

    This is the ``reader`` config group (`conf/reader/default.yaml`); its keys are the
    parameters below. Segmentations are meshed, tetrahedral meshes and `Trajectory` files
    are used as is.

    Parameters
    ----------
    label_map : mapping, optional
        Tissue name (``background``, ``fat``, ``gland``, ``muscle``) -> value or list of values
        in a segmentation, or in ``tissue_field`` of a mesh. Defaults to `DEFAULT_LABELS`.
    spacing : (3,) float
        Voxel size in mm for NumPy segmentations without an affine.
    tissue_field : str
        Cell-data array holding the tissue of each tetrahedron of a mesh file.
    mesher : Mesher
        Meshes segmentations.
    """

    label_map: Mapping[str, int | Sequence[int]] | None = None
    spacing: Sequence[float] = (1.0, 1.0, 1.0)
    tissue_field: str = "tissue"
    mesher: Mesher = field(default_factory=Mesher)

    def read(self, path: str | Path) -> tuple[Trajectory, LabelVolume | None]:
        """The breast in ``path`` and, when the file is a segmentation, its label volume.

        ``metadata["source"]`` is ``path`` unless a `Trajectory` file names its own.

        Raises
        ------
        FileNotFoundError
            The file does not exist.
        ValueError
            The file cannot be read as a breast (see `read_segmentation`, `read_mesh`).
        """
        path = Path(path)
        kind = file_kind(path)
        volume = None
        if kind == "segmentation":
            volume = read_segmentation(path, self.label_map, self.spacing)
            traj = self.mesher(volume)
        elif kind == "trajectory":
            traj = Trajectory.load(path)
        else:
            traj = read_mesh(path, self.tissue_field, self.label_map)
        traj.metadata.setdefault("source", str(path))
        return traj, volume

    def __call__(self, path: str | Path) -> Trajectory:
        """The breast in ``path`` (`read` without the label volume)."""
        return self.read(path)[0]


def to_meshio(traj: Trajectory) -> meshio.Mesh:
    """The mesh with tissue (cell), tissue code and flags (point) fields for ParaView."""
    return meshio.Mesh(
        traj.points,
        [("tetra", traj.cells)],
        cell_data={"tissue": [traj.tissue.astype(np.int32)]},
        point_data={
            "tissue_code": traj.node_tissue_code.astype(np.int32),
            "node_flags": traj.node_flags.astype(np.int32),
        },
    )


def write_mesh(traj: Trajectory, path: str | Path) -> Path:
    """Write the mesh in any meshio format chosen by the suffix (VTU for ParaView), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        meshio.write(tmp, to_meshio(traj))
    return path
