"""The one contract between ``fem/`` and ``datamodules/``: a breast mesh and its FE trajectory.

Coordinates are millimetres in the patient frame RAS+ (x towards the patient's right,
y anterior, z superior/cranial). The anteroposterior axis is y, the cranio-caudal axis z.

The file format is a compressed NumPy archive (``.npz``) whose arrays are the dataclass
fields; ``metadata`` is stored as a JSON string. The schema is versioned
(``SCHEMA_VERSION``) and described in ``docs/trajectory-schema.md``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fem.contract.atomic import atomic_path

SCHEMA_VERSION = 1


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
    plates : (T2, 2, 2) float64
        (y, z) of the chest-side edge of the lower (index 0) and upper (index 1) plate per
        compression step, mm (the paper's features 13-16).
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
            self.plates = np.zeros((len(self.compressed), 2, 2))
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
        if self.plates.shape != (t2, 2, 2):
            raise ValueError(
                f"{source}: field 'plates' must have shape ({t2}, 2, 2), got {self.plates.shape}"
            )
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
        """Read an archive written by `save`; never unpickles."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such trajectory file")
        with np.load(path, allow_pickle=False) as data:
            version = int(data["schema_version"]) if "schema_version" in data else None
            if version != SCHEMA_VERSION:
                raise ValueError(
                    f"{path}: field 'schema_version' is {version}, this code reads {SCHEMA_VERSION}"
                )
            kwargs: dict[str, Any] = {}
            for f in fields(cls):
                if f.name == "metadata":
                    continue
                if f.name not in data:
                    raise ValueError(f"{path}: field '{f.name}' is missing")
                kwargs[f.name] = data[f.name]
            kwargs["metadata"] = json.loads(str(data["metadata"]))
        traj = cls.__new__(cls)
        for k, v in kwargs.items():
            setattr(traj, k, v)
        traj.validate(str(path))
        return traj
