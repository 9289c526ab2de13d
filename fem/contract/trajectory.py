"""The one contract between ``fem/`` and ``datamodules/``: a breast mesh and its FE trajectory.

Coordinates are millimetres in the patient frame RAS+ (x towards the patient's right,
y anterior, z superior/cranial). The anteroposterior axis is y, the cranio-caudal axis z.

The file format is a compressed NumPy archive (``.npz``) whose arrays are the dataclass
fields; ``metadata`` is stored as a JSON string. The schema is versioned
(``SCHEMA_VERSION``) and described in ``docs/trajectory-schema.md``.

Every reader of the project opens files through `reading_file` (and `.npz` archives through
`read_npz`): a missing file is a ``FileNotFoundError``, anything else a library raises on a bad
file (``EOFError``, ``BadZipFile``, ``StopIteration``, parser errors...) one ``ValueError`` that
names the file and says what is wrong with it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fem.contract.atomic import atomic_path
from fem.contract.plates import check_plates, upgrade_v1_plates

SCHEMA_VERSION = 2

#: The schema versions `Trajectory.load` reads (older ones are upgraded on read).
READABLE_VERSIONS = (1, 2)

#: Leading bytes of a NumPy ``.npz`` archive (a ZIP file; the second: an empty one).
NPZ_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")

#: Leading bytes of the kinds of file a user may hand a reader by mistake, for messages.
FILE_SIGNATURES = {
    b"PK\x03\x04": "a ZIP archive (NumPy .npz)",
    b"\x93NUMPY": "a NumPy .npy array",
    b"\x1f\x8b": "gzip-compressed data",
    b"NRRD": "an NRRD image",
    b"\x5c\x01\x00\x00": "a NIfTI-1 image",
    b"\x89PNG": "a PNG image",
    b"\xff\xd8\xff": "a JPEG image",
    b"%PDF": "a PDF document",
    b"\x80": "a Python pickle",
    b"{": "JSON text",
    b"<": "XML text",
}

#: Fields of a trajectory file holding indices, labels or bits: integer arrays.
_INTEGER_FIELDS = ("cells", "tissue", "node_tissue_code", "node_flags", "skin")


class Tissue(IntEnum):
    """Canonical tissue labels of voxels and elements."""

    BACKGROUND = 0
    FAT = 1
    GLAND = 2
    MUSCLE = 3


#: Bit of each tissue in the per-node 3-bit code of the reference paper's Table 2
#: (bit 0 muscle, bit 1 fat, bit 2 gland; interfaces OR their bits).
TISSUE_BIT = {Tissue.MUSCLE: 1, Tissue.FAT: 2, Tissue.GLAND: 4}


class NodeFlag(IntEnum):
    """Bits of ``Trajectory.node_flags``."""

    SKIN = 1  #: node of an outer-surface (skin membrane) triangle
    MUSCLE_INTERFACE = 2  #: node shared by muscle and breast (fat/gland) elements
    UPPER_CONTACT = 4  #: skin node that can meet the upper (cranial) plate
    LOWER_CONTACT = 8  #: skin node that can meet the lower (caudal) plate
    BOUNDARY = 16  #: node on any boundary face (skin or chest-wall cut)


def _empty_steps(n_nodes: int) -> NDArray[np.float64]:
    return np.zeros((0, n_nodes, 3))


@dataclass
class Trajectory:
    """A tetrahedral breast model and, once simulated, its FE trajectories.

    Attributes
    ----------
    points : (N, 3) float64
        Node coordinates of the imaged (initial) geometry, mm.
    cells : (E, 4) int64
        Linear tetrahedra, positively oriented (signed volume > 0).
    tissue : (E,) uint8
        Element tissue label (`Tissue`), majority label of the segmentation inside it.
    node_tissue_code : (N,) uint8
        3-bit code of the paper's Table 2: OR of `TISSUE_BIT` over the incident elements.
    node_flags : (N,) uint8
        Bitmask of `NodeFlag`.
    skin : (S, 3) int64
        Outer-surface triangles of breast (fat/gland) elements, outward normal; the skin membrane.
    unloaded : (T1, N, 3) float64
        Node positions at each recorded step of the unloaded-state step, mm; T1 = 0 before simulation.
    compressed : (T2, N, 3) float64
        Node positions at each recorded compression step, mm; T2 = 0 before simulation.
    plates : (T2, 2, 3, 3) float64
        Frame of the lower (index 0: fixed, detector) and upper (index 1: moving, paddle)
        plate per compression step, rows ``(origin, normal, axis)``: a point of the plate
        surface on its chest-side edge (mm), the unit normal pointing into the breast, the
        unit in-plane direction away from the chest (`fem.contract.plates`).
    compression_ratio : (T2,) float64
        Compression ratio at each compression step, 1 - plate gap / uncompressed thickness.
    metadata : dict
        JSON-serialisable facts: patient, laterality ("L"/"R"), site, breast volume (cm^3),
        glandular fraction, target compressed thickness (mm), mesh quality, ...
    """

    points: NDArray[np.float64]
    cells: NDArray[np.int64]
    tissue: NDArray[np.uint8]
    node_tissue_code: NDArray[np.uint8]
    node_flags: NDArray[np.uint8]
    skin: NDArray[np.int64]
    unloaded: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    compressed: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    plates: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    compression_ratio: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.points)
        if self.unloaded is None:
            self.unloaded = _empty_steps(n)
        if self.compressed is None:
            self.compressed = _empty_steps(n)
        if self.plates is None:
            if len(self.compressed):
                raise ValueError(
                    f"{self.source}: field 'plates' is required when 'compressed' holds steps"
                )
            self.plates = np.zeros((0, 2, 3, 3))
        if self.compression_ratio is None:
            self.compression_ratio = np.zeros(len(self.compressed))
        self.validate()

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_cells(self) -> int:
        return len(self.cells)

    @property
    def reference_shape(self) -> NDArray[np.float64]:
        """(N, 3) the compression's input geometry, mm: the unloaded shape ``unloaded[-1]``
        when the unloaded-state step was simulated (T1 > 0), else the imaged ``points`` (the
        unloaded-state step was skipped; the compression starts from the imaged shape)."""
        return self.unloaded[-1] if len(self.unloaded) else self.points

    @property
    def source(self) -> str:
        """Where the breast came from (``metadata["source"]``, a file name), for messages."""
        return str(self.metadata.get("source", "mesh"))

    def flagged(self, flag: NodeFlag) -> NDArray[np.int64]:
        """Indices of the nodes carrying ``flag``."""
        return np.flatnonzero(self.node_flags & flag)

    def validate(self, source: str = "trajectory") -> None:
        """Check shapes and index ranges; raise ``ValueError`` naming ``source`` and the field."""
        n, e = len(self.points), len(self.cells)
        expected = {
            "points": (n, 3),
            "cells": (e, 4),
            "tissue": (e,),
            "node_tissue_code": (n,),
            "node_flags": (n,),
        }
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"{source}: field '{name}' has shape {getattr(self, name).shape}, expected {shape}"
                )
        if self.skin.ndim != 2 or self.skin.shape[1] != 3:
            raise ValueError(
                f"{source}: field 'skin' must have shape (S, 3), got {self.skin.shape}"
            )
        for name in ("unloaded", "compressed"):
            arr = getattr(self, name)
            if arr.ndim != 3 or arr.shape[1:] != (n, 3):
                raise ValueError(
                    f"{source}: field '{name}' must have shape (T, {n}, 3), got {arr.shape}"
                )
        t2 = len(self.compressed)
        check_plates(self.plates, t2, source)
        if self.compression_ratio.shape != (t2,):
            raise ValueError(
                f"{source}: field 'compression_ratio' must have shape ({t2},), "
                f"got {self.compression_ratio.shape}"
            )
        for name in ("cells", "skin"):
            idx = getattr(self, name)
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"{source}: field '{name}' indexes nodes outside 0..{n - 1}")
        if not np.isfinite(self.points).all():
            raise ValueError(f"{source}: field 'points' contains NaN or infinite coordinates")

    def save(self, path: str | Path) -> Path:
        """Write the archive atomically (temporary name, then rename)."""
        path = Path(path)
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "metadata"}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                schema_version=np.int64(SCHEMA_VERSION),
                metadata=np.array(json.dumps(self.metadata, sort_keys=True)),
                **arrays,
            )
        return path

    @classmethod
    def load(cls, path: str | Path) -> Trajectory:
        """Read an archive written by `save`; never unpickles.

        Raises
        ------
        FileNotFoundError
            The file does not exist.
        ValueError
            The file is empty, truncated, corrupt, not an ``.npz`` archive, or an archive that
            is not a trajectory of this schema (a field missing or of the wrong kind).
        """
        data = read_npz(path, "a trajectory (.npz)")
        if "schema_version" not in data:
            raise ValueError(
                f"{path}: not a trajectory file: field 'schema_version' is missing "
                f"(fields: {', '.join(sorted(data)) or 'none'})"
            )
        version = data["schema_version"]
        known = version.shape == () and version.dtype.kind in "iu"
        if not known or int(version) not in READABLE_VERSIONS:
            raise ValueError(
                f"{path}: field 'schema_version' is {version}, this code reads "
                f"{' and '.join(map(str, READABLE_VERSIONS))} (writes {SCHEMA_VERSION})"
            )
        missing = [f.name for f in fields(cls) if f.name not in data]
        if missing:
            raise ValueError(f"{path}: field(s) {', '.join(map(repr, missing))} missing")
        traj = cls.__new__(cls)
        for f in fields(cls):
            if f.name != "metadata":
                setattr(traj, f.name, _numeric_field(data[f.name], f.name, path))
        if version == 1:
            traj.plates = _upgrade_v1_plates(traj.plates, path)
        traj.metadata = _metadata_field(data["metadata"], path)
        traj.validate(str(path))
        return traj


def _numeric_field(array: NDArray, name: str, path: Path) -> NDArray:
    """``array`` if it has the kind of numbers field ``name`` holds, else a ``ValueError``."""
    kinds = "iu" if name in _INTEGER_FIELDS else "iuf"
    if array.dtype.kind not in kinds:
        expected = "integers" if kinds == "iu" else "numbers"
        raise ValueError(f"{path}: field '{name}' holds {array.dtype} values, not {expected}")
    return array


def _upgrade_v1_plates(plates: NDArray, path: Path) -> NDArray[np.float64]:
    """Version 1's (T2, 2, 2) (y, z) plate edges of the CC plates as version 2's frames."""
    if plates.ndim != 3 or plates.shape[1:] != (2, 2):
        raise ValueError(
            f"{path}: field 'plates' of a version-1 file must have shape (T2, 2, 2), "
            f"got {plates.shape}"
        )
    return upgrade_v1_plates(plates)


def _metadata_field(array: NDArray, path: Path) -> dict[str, Any]:
    """The JSON object stored in the ``metadata`` field."""
    try:
        metadata = json.loads(str(array)) if array.dtype.kind == "U" else None
    except json.JSONDecodeError:
        metadata = None
    if not isinstance(metadata, dict):
        raise ValueError(f"{path}: field 'metadata' is not a JSON object")
    return metadata


def _first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (libraries append stack traces), at most 200 chars."""
    lines = str(exc).strip().splitlines()
    text = f"{type(exc).__name__}: {lines[0]}" if lines else type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _file_problem(head: bytes, what: str) -> str:
    """What a file that does not start like ``what`` is instead."""
    kind = next((k for sig, k in FILE_SIGNATURES.items() if head.startswith(sig)), None)
    return f"it is {kind}, not {what}" if kind else f"it is not {what} (unknown leading bytes)"


@contextmanager
def reading_file(
    path: str | Path, what: str, magic: bytes | tuple[bytes, ...] = ()
) -> Iterator[Path]:
    """Open ``path`` for a library to read as ``what``: the one error policy of every reader.

    On entry the file must exist (else ``FileNotFoundError``), be a non-empty file, and, when
    ``magic`` is given, start with it (else ``ValueError`` saying what the file is instead).
    Any ``Exception`` the block raises becomes one ``ValueError`` naming the file, saying it
    is truncated or corrupt (or, without ``magic``, possibly another kind of file), and
    quoting the library's first line. Keep only library calls in the block, so that the
    readers' own messages pass unchanged.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        The kind of file expected, for messages, e.g. ``"a NIfTI image"``.
    magic : bytes or tuple of bytes
        Leading bytes every valid file starts with (one of them); empty: not checked.

    Yields
    ------
    Path
        ``path``.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: a folder, not a file ({what})")
    with open(path, "rb") as fh:
        head = fh.read(16)
    if not head:
        raise ValueError(f"{path}: the file is empty (0 bytes), not {what}")
    if magic and not head.startswith(magic):
        raise ValueError(f"{path}: {_file_problem(head, what)}")
    try:
        yield path
    except Exception as exc:
        if "allow_pickle" in str(exc):  # NumPy's message (not chained) suggests unsafe loading
            raise ValueError(
                f"{path}: cannot be read as {what}: it holds pickled Python objects, which are "
                "never loaded"
            ) from None
        problem = "truncated or corrupt" if magic else f"truncated, corrupt or not {what}"
        raise ValueError(
            f"{path}: cannot be read as {what}: the file is {problem} ({_first_line(exc)})"
        ) from exc


def read_npz(path: str | Path, what: str = "a NumPy .npz archive") -> dict[str, NDArray]:
    """Every array of an ``.npz`` archive, read eagerly (so that a truncated member fails
    here) and never unpickled; errors as `reading_file`.

    Returns
    -------
    dict
        Field name -> array.
    """
    with reading_file(path, what, NPZ_MAGIC) as p, np.load(p, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}
