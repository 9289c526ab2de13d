"""Reading a user's breast (segmentation or tetrahedral mesh) and writing meshes.

Segmentations: NIfTI (``.nii``, ``.nii.gz``, read with nibabel, affine in RAS+), NRRD
(``.nrrd``, ``.nhdr``, read with pynrrd, its ``space`` converted to RAS+), NumPy (``.npy``
array, or ``.npz`` with ``labels`` and optional ``affine``/``spacing``; axes taken as RAS+).
``orientation`` (a three-letter code) replaces the header's axis directions, or says what
a NumPy array's axes are. The volume is turned to RAS+ axis order (`canonical`). A label map
(tissue name -> file values) turns the file's values into `Tissue` labels; ``skin`` is fat.

Meshes: anything meshio reads (ABAQUS ``.inp``, VTK/VTU, Gmsh ``.msh``, MEDIT ``.mesh``...)
with tetrahedra and a per-cell tissue array (a cell-data field, or for ABAQUS element sets
named after the tissues), used as is.

Lengths are read in ``units`` (mm, cm, m) and converted to mm; a breast whose bounding box is
not ``extent_mm`` across (default `BREAST_EXTENT_MM`) is refused: a file in another unit. Every file goes through
`fem.contract.trajectory.reading_file`: a bad one is one ``ValueError`` naming it.

`BreastReader` reads any of them, and saved `Trajectory` files, the same way for every command.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Mapping, Sequence
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path
from typing import Literal

import meshio
import numpy as np
from numpy.typing import NDArray

from fem.breasts.mesh import Mesher, annotate
from fem.breasts.phantom import LabelVolume
from fem.contract.atomic import atomic_path
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NPZ_MAGIC, Tissue, Trajectory, read_npz, reading_file

SEGMENTATION_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy", ".npz")

#: Tissue names of a label map. Skin voxels are breast: fat (the FE model puts its skin
#: membrane on the mesh's outer surface whatever the label underneath).
TISSUE_NAMES = {
    "background": Tissue.BACKGROUND,
    "fat": Tissue.FAT,
    "gland": Tissue.GLAND,
    "muscle": Tissue.MUSCLE,
    "skin": Tissue.FAT,
}

#: Default label map: the canonical `Tissue` values; no skin label.
DEFAULT_LABELS: dict[str, int | list[int]] = {
    "background": 0,
    "fat": 1,
    "gland": 2,
    "muscle": 3,
    "skin": [],
}

#: Millimetres per unit of a file's lengths (``reader.units``).
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

#: A breast with its chest-wall muscle is this many mm across (the largest side of the
#: bounding box of its tissue), from a small breast to a whole-chest segmentation: the default
#: of ``reader.extent_mm``. A file in metres (0.15 across) or centimetres (15) falls below,
#: one in micrometres above.
BREAST_EXTENT_MM = (20.0, 500.0)

#: Relative volume error of the mesh against the segmentation above which reading warns.
VOLUME_WARNING = 0.05

#: Letter of an orientation code -> (RAS+ axis, sign): the direction an image axis grows to.
AXIS_LETTERS = {"R": (0, 1), "L": (0, -1), "A": (1, 1), "P": (1, -1), "S": (2, 1), "I": (2, -1)}

#: Leading bytes of each segmentation format (NIfTI-1/-2 in either byte order).
SEGMENTATION_MAGIC: dict[str, bytes | tuple[bytes, ...]] = {
    ".nii": (b"\x5c\x01\x00\x00", b"\x00\x00\x01\x5c", b"\x1c\x02\x00\x00", b"\x00\x00\x02\x1c"),
    ".nii.gz": b"\x1f\x8b",
    ".nrrd": b"NRRD",
    ".nhdr": b"NRRD",
    ".npy": b"\x93NUMPY",
    ".npz": NPZ_MAGIC,
}


def file_suffix(path: Path) -> str:
    """The lower-case suffix of ``path``, ``.nii.gz`` counted as one."""
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


# --- settings --------------------------------------------------------------------------------


def _label_values(name: str, values: object) -> list[int]:
    """The integer file values listed for tissue ``name`` (one value, a list, or None)."""
    if values is None:  # reader.label_map.muscle=null: no value
        return []
    items = list(values) if isinstance(values, list | tuple | np.ndarray) else [values]
    ok = all(
        isinstance(v, int | np.integer | float | np.floating)
        and not isinstance(v, bool)
        and float(v).is_integer()
        for v in items
    )
    if not ok:
        raise ValueError(
            f"reader.label_map.{name} must be an integer or a list of integers, got {values!r}"
        )
    return [int(v) for v in items]


def label_lut(label_map: Mapping[str, int | Sequence[int]]) -> dict[int, Tissue]:
    """File value -> `Tissue` of a label map (``reader.label_map``), checked.

    Parameters
    ----------
    label_map : mapping
        Tissue name (`TISSUE_NAMES`: background, fat, gland, muscle, skin; skin is fat) ->
        value or list of values. The map is taken as given, never merged with
        `DEFAULT_LABELS`.

    Raises
    ------
    ValueError
        Not a mapping, an unknown tissue name, a value that is not an integer, or a value
        listed under two tissues (``value 3 is mapped to fat and to muscle``).
    """
    if not isinstance(label_map, Mapping):
        raise ValueError(f"reader.label_map must map tissue names to values, got {label_map!r}")
    lut: dict[int, Tissue] = {}
    owner: dict[int, str] = {}
    for name, values in label_map.items():
        tissue = TISSUE_NAMES.get(str(name).lower())
        if tissue is None:
            raise ValueError(
                f"reader.label_map: unknown tissue {name!r}; use {', '.join(TISSUE_NAMES)}"
            )
        for v in _label_values(name, values):
            if v in owner:
                raise ValueError(
                    f"reader.label_map: value {v} is mapped to {owner[v]} and to {name}; each "
                    "value belongs to one tissue. An override such as "
                    f"reader.label_map.{name}=... merges with the default map key by key: free "
                    f"the value with reader.label_map.{owner[v]}=[] or replace the whole map "
                    "('~reader.label_map' '+reader.label_map={...}')"
                )
            owner[v], lut[v] = str(name), tissue
    return lut


def units_mm(units: str) -> float:
    """Millimetres per unit of ``reader.units`` (mm, cm, m)."""
    if units not in UNITS_MM:
        raise ValueError(
            f"reader.units is {units!r}; use {', '.join(UNITS_MM)} "
            "(the unit of the file's coordinates and voxel sizes)"
        )
    return UNITS_MM[units]


def orientation_matrix(code: str) -> NDArray[np.float64]:
    """The axes of a three-letter orientation code (``reader.orientation``) in RAS+.

    Letter k names the anatomical direction in which array axis k (a mesh: coordinate k)
    grows: R/L (patient's right/left), A/P (anterior/posterior), S/I (superior/inferior), as
    nibabel's axis codes. ``"RAS"`` is the identity, ``"LPS"`` DICOM's frame, ``"RSA"`` an
    image whose third axis runs front-wards. (ITK-SNAP names the opposite ends: its "RAI"
    is "LPS" here.)

    Returns
    -------
    (3, 3) float64
        Column k: the RAS+ unit vector along which axis k grows.
    """
    letters = str(code).upper()
    axes = [AXIS_LETTERS.get(c) for c in letters]
    if len(axes) != 3 or None in axes or sorted(a[0] for a in axes) != [0, 1, 2]:
        raise ValueError(
            f"reader.orientation is {code!r}: give three letters, one of R/L, A/P and S/I "
            "each, the direction in which array axes 0, 1, 2 grow (e.g. RAS, LPS, RSA)"
        )
    matrix = np.zeros((3, 3))
    for k, (axis, sign) in enumerate(axes):
        matrix[axis, k] = sign
    return matrix


def check_spacing(spacing: object, source: str = "reader.spacing") -> NDArray[np.float64]:
    """``spacing`` as three finite voxel sizes > 0, or a ``ValueError`` naming ``source``."""
    try:
        sizes = np.asarray(spacing, float)
    except (TypeError, ValueError):
        sizes = np.zeros(0)
    if sizes.shape != (3,) or not (np.isfinite(sizes) & (sizes > 0)).all():
        raise ValueError(
            f"{source} must be three finite voxel sizes > 0 (in reader.units), got {spacing!r}"
        )
    return sizes


# --- segmentations ---------------------------------------------------------------------------


def _nrrd_affine(header: Mapping, path: Path, trust_space: bool) -> NDArray[np.float64]:
    """Voxel index -> RAS+ of an NRRD header; without ``trust_space`` its ``space`` is ignored
    (``reader.orientation`` replaces the directions)."""
    try:
        directions = np.asarray(header.get("space directions", np.eye(3)), float)
    except (TypeError, ValueError):
        directions = np.zeros(0)
    if directions.shape != (3, 3) or not np.isfinite(directions).all():
        raise ValueError(
            f"{path}: field 'space directions' must be a 3x3 matrix for a 3-D label volume"
        )
    try:
        origin = np.asarray(header.get("space origin", np.zeros(3)), float).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: field 'space origin' must be three numbers") from None
    space = str(header.get("space", "right-anterior-superior")).lower() if trust_space else "ras"
    flip = {
        "right-anterior-superior": [1, 1, 1],
        "ras": [1, 1, 1],
        "left-posterior-superior": [-1, -1, 1],
        "lps": [-1, -1, 1],
        "left-anterior-superior": [-1, 1, 1],
        "las": [-1, 1, 1],
    }
    if space not in flip:
        raise ValueError(
            f"{path}: field 'space' is {space!r}; supported: {sorted(flip)}; or give the axes' "
            "directions with reader.orientation"
        )
    affine = np.eye(4)
    affine[:3, :3] = np.diag(flip[space]) @ directions.T  # columns: world step per index
    affine[:3, 3] = np.asarray(flip[space]) * origin
    return affine


def _read_volume(
    path: Path, spacing: NDArray, trust_header: bool
) -> tuple[NDArray, NDArray[np.float64]]:
    """The file's array and voxel index -> world affine (file units), as the file gives them."""
    suffix = file_suffix(path)
    if suffix not in SEGMENTATION_MAGIC:
        raise ValueError(
            f"{path}: unknown segmentation format; expected one of {SEGMENTATION_SUFFIXES}"
        )
    what, magic = f"a {suffix} segmentation", SEGMENTATION_MAGIC[suffix]
    if suffix in (".nii", ".nii.gz"):
        import nibabel

        with reading_file(path, what, magic) as p:
            img = nibabel.load(str(p))
            return np.asanyarray(img.dataobj), np.asarray(img.affine, float)
    if suffix in (".nrrd", ".nhdr"):
        import nrrd

        with reading_file(path, what, magic) as p:
            data, header = nrrd.read(str(p))
        return data, _nrrd_affine(header, path, trust_header)
    if suffix == ".npy":
        with reading_file(path, what, magic) as p:
            data = np.load(p, allow_pickle=False)
        return data, np.diag([*spacing, 1.0])
    z = read_npz(path, what)
    if "labels" not in z:
        raise ValueError(f"{path}: field 'labels' is missing (found {sorted(z)})")
    if "affine" in z:
        return z["labels"], z["affine"]
    if "spacing" in z:
        spacing = check_spacing(z["spacing"], f"{path}: field 'spacing'")
    return z["labels"], np.diag([*spacing, 1.0])


def _check_affine(affine: NDArray, path: Path) -> NDArray[np.float64]:
    """A finite, non-degenerate voxel index -> world affine, as float64 (a copy)."""
    affine = np.asarray(affine)
    if affine.shape != (4, 4) or affine.dtype.kind not in "iuf" or not np.isfinite(affine).all():
        raise ValueError(
            f"{path}: the affine (voxel -> world) must be a finite 4x4 matrix, "
            f"got {affine.dtype} of shape {affine.shape}"
        )
    affine = affine.astype(float)
    sizes = np.linalg.norm(affine[:3, :3], axis=0)
    if not (sizes > 0).all() or abs(np.linalg.det(affine[:3, :3])) <= 1e-6 * sizes.prod():
        raise ValueError(
            f"{path}: the affine (voxel -> world) is degenerate, voxel sizes "
            f"{sizes.round(6).tolist()}: a corrupt header or spacing"
        )
    return affine


def _label_array(data: NDArray, path: Path) -> NDArray[np.integer]:
    """The file's array as 3-D integers (trailing axes of length 1 dropped)."""
    data = np.asarray(data)
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise ValueError(f"{path}: field 'labels' must be a 3-D array, got shape {data.shape}")
    if data.dtype.kind == "b":
        return data.astype(np.uint8)
    if data.dtype.kind not in "iuf":
        raise ValueError(f"{path}: field 'labels' holds {data.dtype} values, not integer labels")
    if data.dtype.kind == "f":
        if not (np.isfinite(data) & (data == np.round(data))).all():
            raise ValueError(f"{path}: field 'labels' holds non-integer values ({data.dtype})")
        return data.astype(np.int64)
    return data


def _map_labels(
    data: NDArray, lut: dict[int, Tissue], path: Path, label_map: Mapping
) -> NDArray[np.uint8]:
    """`Tissue` labels of the file's values; every value must be in the label map."""
    values = np.unique(data)
    unknown = [int(v) for v in values if int(v) not in lut]
    if unknown:
        raise ValueError(
            f"{path}: field 'labels' contains value(s) {unknown} that are not in the label map "
            f"{dict(label_map)} (reader.label_map)"
        )
    labels = np.zeros(data.shape, np.uint8)
    for v in values:
        labels[data == v] = lut[int(v)]
    return labels


def canonical(labels: NDArray, affine: NDArray[np.float64]) -> tuple[NDArray, NDArray[np.float64]]:
    """The volume with its array axes reordered and flipped to grow towards R, A, S (the
    closest to the affine's axes), and the affine that keeps every voxel where it was."""
    from nibabel import orientations

    ornt = orientations.io_orientation(affine)
    turned = np.ascontiguousarray(orientations.apply_orientation(labels, ornt))
    return turned, affine @ orientations.inv_ornt_aff(ornt, labels.shape)


def tissue_extent(labels: NDArray, affine: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3,) mm: the sides of the RAS+ bounding box of the non-background voxels."""
    ranges = []
    for axis in range(3):
        others = tuple(a for a in range(3) if a != axis)
        hit = np.flatnonzero((labels != 0).any(axis=others))
        ranges.append((hit[0] - 0.5, hit[-1] + 0.5))
    corners = np.array(np.meshgrid(*ranges, indexing="ij")).reshape(3, -1).T
    return np.ptp(corners @ affine[:3, :3].T, axis=0)


def check_extent_range(extent_mm: object) -> tuple[float, float]:
    """``reader.extent_mm`` as (smallest, largest) mm, two finite numbers 0 < lo < hi."""
    try:
        lo, hi = (float(x) for x in extent_mm)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        lo = hi = np.nan
    if not (np.isfinite([lo, hi]).all() and 0 < lo < hi):
        raise ValueError(
            f"reader.extent_mm must be two sizes 0 < smallest < largest in mm, got {extent_mm!r}"
        )
    return lo, hi


def check_extent(
    size: NDArray,
    source: str | Path,
    units: str,
    extent_mm: Sequence[float] = BREAST_EXTENT_MM,
) -> None:
    """Refuse a breast whose bounding box ``size`` (3,) mm is not ``extent_mm`` across (its
    largest side), naming ``source`` and the settings ``reader.units`` and ``reader.extent_mm``."""
    lo, hi = check_extent_range(extent_mm)
    largest = float(np.max(size))
    if not lo <= largest <= hi:
        raise ValueError(
            f"{source}: the breast is {largest:.3g} mm across (bounding box "
            f"{[float(f'{s:.3g}') for s in size]} mm, read in reader.units={units}); a breast "
            f"is {lo:g} to {hi:g} mm across (reader.extent_mm). Is the file in another unit? "
            f"Set reader.units ({', '.join(UNITS_MM)}) to its unit, or check its voxel size"
        )


def read_segmentation(
    path: str | Path,
    label_map: Mapping[str, int | Sequence[int]] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    units: str = "mm",
    orientation: str | None = None,
    extent_mm: Sequence[float] = BREAST_EXTENT_MM,
) -> LabelVolume:
    """Read a labelled breast segmentation as canonical `Tissue` labels.

    Parameters
    ----------
    path : str or Path
        NIfTI, NRRD or NumPy file.
    label_map : mapping, optional
        Tissue name (``background``, ``fat``, ``gland``, ``muscle``, ``skin``) -> value or
        list of values in the file; replaces `DEFAULT_LABELS` (never merged with it). Skin
        voxels are fat: the breast's outer layer, under the FE model's skin membrane.
    spacing : (3,) float
        Voxel size in ``units`` for NumPy arrays without an affine.
    units : {"mm", "cm", "m"}
        Unit of the file's lengths (affine, voxel sizes, ``spacing``); converted to mm.
    orientation : str, optional
        Three-letter code (`orientation_matrix`) of the directions the array axes grow to;
        replaces the header's directions and origin (voxel sizes kept; voxel (0, 0, 0) at the
        origin). ``None``: the header's affine (NumPy arrays: RAS).
    extent_mm : (2,) float
        Smallest and largest plausible breast, mm: the largest side of the bounding box of
        the non-background voxels must lie between them.

    Returns
    -------
    LabelVolume
        Labels with array axes growing towards R, A, S (`canonical`), affine in mm.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        A bad setting; an empty, truncated, corrupt or foreign file; an array that is not 3-D
        integers; values missing from the label map; no fat or gland; a degenerate affine; or
        a breast not ``extent_mm`` across (a file in another unit).
    """
    path = Path(path)
    check_extent_range(extent_mm)
    label_map = DEFAULT_LABELS if label_map is None else label_map
    lut = label_lut(label_map)
    scale = units_mm(units)
    axes = None if orientation is None else orientation_matrix(orientation)
    data, affine = _read_volume(path, check_spacing(spacing), trust_header=axes is None)
    data = _label_array(data, path)
    affine = _check_affine(affine, path)
    affine[:3] *= scale
    if axes is not None:
        affine[:3, :3] = axes * np.linalg.norm(affine[:3, :3], axis=0)
        affine[:3, 3] = 0.0
    labels, affine = canonical(_map_labels(data, lut, path, label_map), affine)
    if not np.isin(labels, (Tissue.FAT, Tissue.GLAND)).any():
        raise ValueError(
            f"{path}: no breast labels (fat or gland) in field 'labels' with label map "
            f"{dict(label_map)}"
        )
    check_extent(tissue_extent(labels, affine), path, units, extent_mm)
    return LabelVolume(labels, affine, str(path))


# --- meshes ----------------------------------------------------------------------------------


def _meshio_read(path: Path) -> meshio.Mesh:
    """``meshio.read``, its printed complaints kept: when no reader accepts the file, meshio
    prints why and calls ``sys.exit``, which becomes a ``ValueError`` naming the file."""
    printed = StringIO()
    with reading_file(path, "a mesh meshio reads"):
        try:
            with redirect_stdout(printed), redirect_stderr(printed):
                mesh = meshio.read(path)
        except SystemExit:  # a BaseException: it would pass `except Exception`
            raise meshio.ReadError(" ".join(printed.getvalue().split())) from None
    sys.stderr.write(printed.getvalue())  # warnings of a successful read
    return mesh


def read_mesh(
    path: str | Path,
    tissue_field: str = "tissue",
    tissue_values: Mapping[str, int | Sequence[int]] | None = None,
    units: str = "mm",
    orientation: str | None = None,
    extent_mm: Sequence[float] = BREAST_EXTENT_MM,
) -> Trajectory:
    """Read a tetrahedral breast mesh (any meshio format) with a per-cell tissue array.

    Parameters
    ----------
    path : str or Path
        Mesh file.
    tissue_field : str
        Cell-data array holding the tissue of each tetrahedron. For files without it (e.g.
        ABAQUS ``.inp``), element sets named ``fat``, ``gland``, ``muscle``, ``skin`` (any
        case) are used.
    tissue_values : mapping, optional
        Tissue name -> value(s) in ``tissue_field`` (a label map, `label_lut`); defaults to
        the canonical labels. Skin elements are fat.
    units : {"mm", "cm", "m"}
        Unit of the file's coordinates; converted to mm.
    orientation : str, optional
        Three-letter code (`orientation_matrix`) of the directions the x, y, z coordinates
        grow to; ``None``: RAS+.
    extent_mm : (2,) float
        Smallest and largest plausible breast, mm (the largest side of the bounding box).

    A mesh whose tetrahedra are all negatively oriented (a convention of some writers, or a
    mirroring ``orientation``) is reoriented; a mix of orientations, or flat elements, is
    refused, as is a breast not ``extent_mm`` across (a file in another unit).
    """
    path = Path(path)
    check_extent_range(extent_mm)
    lut = label_lut(DEFAULT_LABELS if tissue_values is None else tissue_values)
    lut = {v: t for v, t in lut.items() if t != Tissue.BACKGROUND}
    scale = units_mm(units)
    axes = np.eye(3) if orientation is None else orientation_matrix(orientation)
    mesh = _meshio_read(path)
    blocks = [i for i, c in enumerate(mesh.cells) if c.type == "tetra"]
    if not blocks:
        found = sorted({c.type for c in mesh.cells}) or ["no cells"]
        raise ValueError(f"{path}: no tetrahedral cells (found: {', '.join(found)})")
    cells = np.vstack([mesh.cells[i].data for i in blocks]).astype(np.int64)
    points = np.asarray(mesh.points, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: field 'points' must be 3-D, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{path}: field 'points' contains NaN or infinite coordinates")
    if cells.min() < 0 or cells.max() >= len(points):
        raise ValueError(f"{path}: field 'cells' indexes nodes outside 0..{len(points) - 1}")
    points = scale * points @ axes.T
    check_extent(np.ptp(points, axis=0), path, units, extent_mm)
    if tissue_field in mesh.cell_data:
        raw = np.concatenate([np.asarray(mesh.cell_data[tissue_field][i]).ravel() for i in blocks])
        tissue = np.zeros(len(raw), np.uint8)
        for value, t in lut.items():
            tissue[raw == value] = t
        unknown = np.unique(raw[tissue == 0])
        if unknown.size:
            raise ValueError(
                f"{path}: cell field '{tissue_field}' contains value(s) {unknown.tolist()} "
                f"that are not breast tissues of the label map (reader.label_map)"
            )
    else:
        tissue = _tissue_from_sets(mesh, blocks, path, tissue_field)
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
        t = TISSUE_NAMES.get(name.strip().lower(), Tissue.BACKGROUND)
        if t == Tissue.BACKGROUND:
            continue
        for k, i in enumerate(blocks):
            idx = np.asarray(per_block[i]) if i < len(per_block) else np.zeros(0, int)
            tissue[offsets[k] + idx.astype(int)] = t
    if (tissue == 0).all():
        raise ValueError(
            f"{path}: no per-cell tissue: cell field '{field}' is missing "
            f"(cell fields: {sorted(mesh.cell_data)}) and no element sets are named "
            f"fat/gland/muscle/skin (sets: {sorted(mesh.cell_sets)})"
        )
    if (tissue == 0).any():
        raise ValueError(
            f"{path}: {(tissue == 0).sum()} tetrahedra belong to no fat/gland/muscle/skin element set"
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
        with (
            reading_file(path, "a NumPy .npz archive", NPZ_MAGIC) as p,
            np.load(p, allow_pickle=False) as z,
        ):
            return "trajectory" if "schema_version" in z.files else "segmentation"
    return "segmentation" if file_suffix(path) in SEGMENTATION_SUFFIXES else "mesh"


def warn_volume_error(traj: Trajectory, source: str | Path, mesher: Mesher) -> None:
    """Warn when the mesh's volume misses the segmentation's by more than `VOLUME_WARNING`
    (``traj.metadata["mesh"]``, as ``mesher`` writes it, meshed from the file ``source``)."""
    info = traj.metadata["mesh"]
    error = info["volume_error"]
    if abs(error) > VOLUME_WARNING:
        warnings.warn(
            f"{source}: the mesh's volume {info['mesh_volume_cm3']:.1f} cm^3 misses the "
            f"segmentation's {info['segmented_volume_cm3']:.1f} cm^3 by {100 * error:+.1f} % "
            f"(more than {100 * VOLUME_WARNING:g} %): raise reader.mesher.target_elements "
            f"(now {mesher.target_elements}) for a finer mesh, or look for thin layers and "
            "detached parts in the segmentation (the mesh keeps its largest connected part)",
            stacklevel=3,
        )


@dataclass(frozen=True)
class BreastReader:
    """A user's breast file -> mesh-only `Trajectory`: the input loader of every command.

    This is the ``reader`` config group (`conf/reader/default.yaml`); its keys are the
    parameters below, all checked when the reader is made, before any file is read.
    Segmentations are meshed (with a warning when the mesh's volume misses the
    segmentation's by more than `VOLUME_WARNING`); tetrahedral meshes and `Trajectory` files
    are used as is.

    Parameters
    ----------
    label_map : mapping, optional
        Tissue name (``background``, ``fat``, ``gland``, ``muscle``, ``skin``) -> value or
        list of values in a segmentation, or in ``tissue_field`` of a mesh. Replaces
        `DEFAULT_LABELS` (never merged with it); a value under two tissues is an error. Skin
        is fat (the FE model's skin membrane covers the mesh's outer surface).
    spacing : (3,) float
        Voxel size in ``units`` for NumPy segmentations without an affine.
    tissue_field : str
        Cell-data array holding the tissue of each tetrahedron of a mesh file.
    mesher : Mesher
        Meshes segmentations.
    units : {"mm", "cm", "m"}
        Unit of a segmentation's or mesh's lengths, converted to mm.
    orientation : str, optional
        Three-letter code of the directions in which a segmentation's array axes (a mesh's
        x, y, z) grow, e.g. ``"RSA"``: axis 0 to the patient's right, axis 1 superior, axis 2
        anterior (`orientation_matrix`). Replaces a header's directions and origin; ``None``
        trusts the header (NumPy arrays and meshes: RAS).
    extent_mm : (2,) float
        Smallest and largest plausible breast, mm: a segmentation's tissue or a mesh whose
        bounding box's largest side (after ``units``) lies outside is refused, a file in
        another unit being the likely cause. Default `BREAST_EXTENT_MM`.

    `Trajectory` files are this project's, in mm and RAS+: ``units`` and ``orientation``
    must keep their defaults for them.
    """

    label_map: Mapping[str, int | Sequence[int]] | None = None
    spacing: Sequence[float] = (1.0, 1.0, 1.0)
    tissue_field: str = "tissue"
    mesher: Mesher = field(default_factory=Mesher)
    units: str = "mm"
    orientation: str | None = None
    extent_mm: Sequence[float] = BREAST_EXTENT_MM

    def __post_init__(self) -> None:
        label_lut(DEFAULT_LABELS if self.label_map is None else self.label_map)
        check_spacing(self.spacing)
        units_mm(self.units)
        check_extent_range(self.extent_mm)
        if self.orientation is not None:
            orientation_matrix(self.orientation)

    def read(self, path: str | Path) -> tuple[Trajectory, LabelVolume | None]:
        """The breast in ``path`` and, when the file is a segmentation, its label volume.

        ``metadata["source"]`` is ``path`` unless a `Trajectory` file names its own.

        Raises
        ------
        FileNotFoundError
            The file does not exist.
        ValueError
            The file cannot be read as a breast (see `read_segmentation`, `read_mesh`,
            `Trajectory.load`).
        """
        path = Path(path)
        kind = file_kind(path)
        volume = None
        if kind == "segmentation":
            volume = read_segmentation(
                path, self.label_map, self.spacing, self.units, self.orientation, self.extent_mm
            )
            traj = self.mesher(volume)
            warn_volume_error(traj, path, self.mesher)
        elif kind == "trajectory":
            if (self.units, self.orientation) != ("mm", None):
                raise ValueError(
                    f"{path}: a trajectory file is in mm and RAS+; reader.units={self.units} "
                    f"and reader.orientation={self.orientation or 'null'} apply to "
                    "segmentations and meshes only: leave them at mm and null"
                )
            traj = Trajectory.load(path)
        else:
            traj = read_mesh(
                path,
                self.tissue_field,
                self.label_map,
                self.units,
                self.orientation,
                self.extent_mm,
            )
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
