"""Per-node, per-step features of the reference paper (section 2.2) and its normalisation (eq. 1).

One instance is one node at one recorded step. The unloaded-state model sees 11 features, the
compression model 22 (`UNLOADED_FEATURES`, `COMPRESSION_FEATURES`; units and definitions in
docs/features.md); the targets are the node's coordinates at that step. Coordinates, plate
positions and targets are z-scored per breast (equation 1): ``(v - mu) / sigma`` with ``mu``
the mean node position of the step's input geometry and ``sigma`` the root-mean-square
distance of its nodes from ``mu`` (one scale for all three axes, so shapes are not distorted);
`Normalization` keeps both to map predictions back to millimetres.

The input geometry of the unloaded-state step is the imaged mesh (``points``); that of the
compression step is the unloaded shape (`Trajectory.reference_shape`: ``unloaded[-1]``, or
``points`` when the unloaded-state step was skipped), the compression's stress-free
reference, so a predicted unloaded state can feed the compression model. The compression's
coordinates, plates and targets are expressed in the frame of the lower plate (a rotation,
`Normalization.rotation`), so cranio-caudal and oblique compressions share one model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fem.contract.plates import NORMAL, ORIGIN, plate_basis
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory

TISSUES = (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)

#: Features 1-11 (unloaded state and compression).
UNLOADED_FEATURES = (
    "x",
    "y",
    "z",
    "step",
    "volume_fraction_fat",
    "volume_fraction_gland",
    "volume_fraction_muscle",
    "volume_mm3",
    "element_fraction_fat",
    "element_fraction_gland",
    "element_fraction_muscle",
)

#: Features 1-22 (compression).
COMPRESSION_FEATURES = (
    *UNLOADED_FEATURES,
    "upper_plate_displacement",
    "lower_plate_edge_y",
    "lower_plate_edge_z",
    "upper_plate_edge_y",
    "upper_plate_edge_z",
    "upper_contact",
    "skin",
    "tissue_bit_2_gland",
    "tissue_bit_1_fat",
    "tissue_bit_0_muscle",
    "laterality",
)

#: Value of feature 22 per laterality.
LATERALITY = {"L": 0.0, "R": 1.0}

#: The features of each simulation step's model.
STEP_FEATURES = {"unloaded": UNLOADED_FEATURES, "compression": COMPRESSION_FEATURES}


#: The revision of each input whose definition changed after models were trained on it; every
#: other input is at revision 1. A model file stores the revisions it was trained on
#: (`FeatureSchema.revisions`) and is refused when they are not this code's, because the same
#: name then carries other numbers. Revision 2 of the plate edges (2026-12-02): the origins of
#: the plate frames of Trajectory schema 2, in the lower plate's frame.
REVISIONS: dict[str, int] = {
    "lower_plate_edge_y": 2,
    "lower_plate_edge_z": 2,
    "upper_plate_edge_y": 2,
    "upper_plate_edge_z": 2,
}


def revisions_of(features: tuple[str, ...]) -> tuple[tuple[str, int], ...]:
    """This code's revision of each of ``features`` past revision 1, as (name, revision)."""
    return tuple((f, REVISIONS[f]) for f in features if REVISIONS.get(f, 1) > 1)


@dataclass(frozen=True)
class FeatureSchema:
    """What a trained model takes: its simulation step, its inputs in order, the revision of
    each input whose definition changed (`REVISIONS`; a file without them was trained on
    revision 1 of every input) and the number of recorded steps it was trained on (the trees
    see the step index as feature 4). Every model file stores it, so a model is never fed
    inputs it was not trained on."""

    step: str
    features: tuple[str, ...]
    n_steps: int
    revisions: tuple[tuple[str, int], ...] = ()

    @classmethod
    def current(cls, step: str, features: tuple[str, ...], n_steps: int) -> FeatureSchema:
        """The schema of ``features`` as this code computes them (their `REVISIONS`)."""
        return cls(step, tuple(features), int(n_steps), revisions_of(tuple(features)))

    @classmethod
    def of(cls, step: str, n_steps: int) -> FeatureSchema:
        """This code's schema of the paper features of ``step`` with ``n_steps`` recorded steps."""
        if step not in STEP_FEATURES:
            raise ValueError(f"step must be one of {sorted(STEP_FEATURES)}, got {step!r}")
        return cls.current(step, STEP_FEATURES[step], n_steps)

    def to_json(self) -> str:
        d = {"step": self.step, "features": list(self.features), "n_steps": self.n_steps}
        if self.revisions:
            d["revisions"] = dict(self.revisions)
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str, source: str = "model") -> FeatureSchema:
        try:
            d = json.loads(text)
            revisions = tuple((str(f), int(r)) for f, r in d.get("revisions", {}).items())
            return cls(
                str(d["step"]), tuple(str(f) for f in d["features"]), int(d["n_steps"]), revisions
            )
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{source}: unreadable feature schema {text!r}: {exc}") from exc

    def check(
        self, step: str, source: str = "model", expected: tuple[str, ...] | None = None
    ) -> None:
        """Refuse a model trained for another step or on other inputs than this code's: the
        step's `STEP_FEATURES`, or ``expected`` (a graph model's inputs), at their current
        `REVISIONS`."""
        if step != self.step:
            raise ValueError(
                f"{source}: the model predicts the {self.step} step, not the {step} step"
            )
        expected = STEP_FEATURES.get(step) if expected is None else expected
        if self.features != expected:
            raise ValueError(
                f"{source}: the model was trained on the features {list(self.features)}, this "
                f"version computes {list(expected or ())} for the {step} step; retrain it"
            )
        stored, now = dict(self.revisions), dict(revisions_of(expected))
        changed = [f for f in self.features if stored.get(f, 1) != now.get(f, 1)]
        if changed:
            revised = ", ".join(f"{f} {stored.get(f, 1)} -> {now.get(f, 1)}" for f in changed)
            raise ValueError(
                f"{source}: the model was trained on older definitions of some inputs of the "
                f"{step} step (revision trained on -> this version's: {revised}; "
                "datamodules.features.REVISIONS says what changed); retrain it"
            )


@dataclass(frozen=True)
class Normalization:
    """Per-breast z-score of coordinates (equation 1) in a frame: ``(v @ rotation - mean) / scale``.

    The compression's coordinates are expressed in the lower plate's frame
    (`fem.contract.plates.plate_basis`), so that a cranio-caudal and a mediolateral-oblique
    compression look alike to a model; ``rotation`` turns patient-frame coordinates into that
    frame (``v' = rotation.T @ v``) before the z-score, and `invert` turns predictions back
    into the patient frame. ``None`` is the identity (the unloaded-state step, cranio-caudal
    plates, and every normalisation stored before rotations existed): no arithmetic is done,
    so those features are bit-identical to the unrotated ones.

    Attributes
    ----------
    mean : (3,) float64
        Mean node position of the input geometry in the frame, mm.
    scale : float
        Root-mean-square distance of the nodes from ``mean``, mm.
    rotation : (3, 3) float64 or None
        Columns: the frame's axes in the patient frame; ``None``: the patient frame itself.
    """

    mean: NDArray
    scale: float
    rotation: NDArray | None = None

    @classmethod
    def of(cls, points: NDArray, rotation: NDArray | None = None) -> Normalization:
        """The normalisation of a geometry ``points`` (N, 3), mm, in the frame ``rotation``
        (3, 3) (columns: the frame's axes; an exact identity is stored as ``None``)."""
        if rotation is not None:
            rotation = np.asarray(rotation, np.float64)
            if np.array_equal(rotation, np.eye(3)):
                rotation = None
        points = points if rotation is None else points @ rotation
        mean = points.mean(axis=0)
        return cls(mean, float(np.sqrt(((points - mean) ** 2).sum(axis=1).mean())), rotation)

    def to_frame(self, v: NDArray) -> NDArray:
        """Patient-frame coordinates ``v`` (..., 3) in the normalisation's frame, mm."""
        return v if self.rotation is None else v @ self.rotation

    def from_frame(self, v: NDArray) -> NDArray:
        """Frame coordinates ``v`` (..., 3) back in the patient frame, mm."""
        return v if self.rotation is None else v @ self.rotation.T

    def _check_axes(self, axes: slice | list[int]) -> None:
        if self.rotation is not None and axes != slice(None):
            raise ValueError("a rotated normalisation applies to whole (x, y, z) coordinates")

    def apply(self, v: NDArray, axes: slice | list[int] = slice(None)) -> NDArray:
        """Normalise patient-frame coordinates ``v`` (..., k) whose last axis holds the axes
        ``axes`` (all three when the normalisation has a rotation)."""
        self._check_axes(axes)
        return (self.to_frame(v) - self.mean[axes]) / self.scale

    def invert(self, v: NDArray, axes: slice | list[int] = slice(None)) -> NDArray:
        """Patient-frame millimetres of normalised coordinates ``v`` (..., k)."""
        self._check_axes(axes)
        return self.from_frame(v * self.scale + self.mean[axes])

    def to_json(self) -> dict:
        """The JSON-serialisable fields (``rotation`` only when there is one)."""
        out = {"mean": np.asarray(self.mean).tolist(), "scale": float(self.scale)}
        if self.rotation is not None:
            out["rotation"] = self.rotation.tolist()
        return out

    @classmethod
    def from_json(cls, d: dict) -> Normalization:
        """Of `to_json`'s fields; without ``rotation`` (every file written before rotations
        existed) the identity."""
        rotation = d.get("rotation")
        return cls(
            np.asarray(d["mean"], np.float64),
            float(d["scale"]),
            None if rotation is None else np.asarray(rotation, np.float64).reshape(3, 3),
        )


def tissue_descriptors(traj: Trajectory) -> NDArray[np.float64]:
    """Features 5-11 of a breast: volume fractions (fat, gland, muscle), mesh volume (mm^3),
    element fractions (fat, gland, muscle), from the mesh itself. Shape (7,)."""
    volumes = signed_volume(traj.points, traj.cells)
    total = volumes.sum()
    volume_fraction = [volumes[traj.tissue == t].sum() / total for t in TISSUES]
    element_fraction = [np.mean(traj.tissue == t) for t in TISSUES]
    return np.array([*volume_fraction, total, *element_fraction])


def _base_features(
    geometry: NDArray, n_steps: int, descriptors: NDArray, norm: Normalization
) -> NDArray[np.float32]:
    """Features 1-11 for every step and node, shape (T, N, 11)."""
    n = len(geometry)
    out = np.empty((n_steps, n, len(UNLOADED_FEATURES)), np.float32)
    out[:, :, 0:3] = norm.apply(geometry)
    out[:, :, 3] = np.arange(1, n_steps + 1)[:, None]
    out[:, :, 4:11] = descriptors
    return out


def unloaded_inputs(traj: Trajectory, n_steps: int) -> tuple[NDArray[np.float32], Normalization]:
    """Unloaded-state features of a breast mesh, simulated or not.

    Returns
    -------
    features : (n_steps, N, 11) float32
        `UNLOADED_FEATURES` per recorded step and node.
    normalization : Normalization
        Of the imaged geometry; it maps the model's outputs back to millimetres.
    """
    norm = Normalization.of(traj.points)
    return _base_features(traj.points, n_steps, tissue_descriptors(traj), norm), norm


def unloaded_features(
    traj: Trajectory,
) -> tuple[NDArray[np.float32], NDArray[np.float32], Normalization]:
    """Unloaded-state instances of a simulated breast.

    Returns
    -------
    features : (T1, N, 11) float32
        `UNLOADED_FEATURES` per step and node.
    targets : (T1, N, 3) float32
        Normalised node coordinates per step.
    normalization : Normalization
        Of the imaged geometry; ``normalization.invert(targets)`` gives millimetres.
    """
    features, norm = unloaded_inputs(traj, len(traj.unloaded))
    return features, norm.apply(traj.unloaded).astype(np.float32), norm


def facing_plate(traj: Trajectory, normal: NDArray) -> NDArray[np.bool_]:
    """Skin nodes that can meet a plate with the unit normal ``normal`` (3,): those whose
    area-weighted skin normal (imaged geometry) points against it, ``n . normal < 0``.

    For the upper cranio-caudal plate (normal (0, 0, -1)) this is the rule of
    `fem.breasts.mesh.annotate`'s ``NodeFlag.UPPER_CONTACT`` (a positive z component),
    evaluated in the same order, so the same bits. Shape (N,).
    """
    p = traj.points[traj.skin]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    vertex_normal = np.zeros((traj.n_nodes, 3))
    for k in range(3):
        np.add.at(vertex_normal, traj.skin[:, k], area_normal)
    skin_nodes = (traj.node_flags & NodeFlag.SKIN) > 0
    return skin_nodes & (vertex_normal @ np.asarray(normal, np.float64) < 0)


#: Normal of the upper plate of a cranio-caudal compression.
CC_UPPER_NORMAL = np.array([0.0, 0.0, -1.0])


def upper_contact(traj: Trajectory, plates: NDArray) -> NDArray[np.bool_]:
    """Feature 17: the nodes that can meet the upper plate ``plates[0, 1]`` (T, 2, 3, 3).

    Cranio-caudal plates (upper normal exactly (0, 0, -1)) take the stored
    ``NodeFlag.UPPER_CONTACT``, which `fem.breasts.mesh.annotate` computed by the rule of
    `facing_plate` for that normal; other plates (an oblique view) evaluate the rule against
    their upper plate's normal. Shape (N,).
    """
    normal = plates[0, 1, NORMAL]
    if np.array_equal(normal, CC_UPPER_NORMAL):
        return (traj.node_flags & NodeFlag.UPPER_CONTACT) > 0
    return facing_plate(traj, normal)


def compression_inputs(
    traj: Trajectory, unloaded: NDArray, plates: NDArray, compression_ratio: NDArray
) -> tuple[NDArray[np.float32], Normalization]:
    """Compression features of a breast mesh from its unloaded shape and the plates' schedule
    (simulated, or predicted and placed by `fem.engine.boundary.plate_schedule`).

    Coordinates are expressed in the frame of the lower plate at the first step
    (`fem.contract.plates.plate_basis` of ``plates[0, 0]``): x' along its chest-side edge,
    y' away from the chest, z' along its normal. For cranio-caudal plates that frame is the
    patient frame and the features are those of the paper; an oblique compression gets the
    features its cranio-caudal counterpart would.

    Parameters
    ----------
    traj : Trajectory
        The mesh: cells, tissues, node flags and ``metadata["laterality"]``.
    unloaded : (N, 3)
        The compression's input geometry (`Trajectory.reference_shape`), mm.
    plates : (T, 2, 3, 3)
        Frames (origin, normal, axis) of the lower and upper plate per recorded step,
        mm (`fem.contract.plates`).
    compression_ratio : (T,)
        Compression ratio per recorded step.

    Returns
    -------
    features : (T, N, 22) float32
        `COMPRESSION_FEATURES` per recorded step and node.
    normalization : Normalization
        Of the unloaded shape in the lower plate's frame; its `Normalization.invert` gives
        patient-frame millimetres.

    Raises
    ------
    ValueError
        The metadata has no laterality.
    """
    source = traj.source
    laterality = traj.metadata.get("laterality")
    if laterality not in LATERALITY:
        raise ValueError(
            f"{source}: metadata field 'laterality' must be 'L' or 'R', got {laterality!r}"
        )
    plates = np.asarray(plates, np.float64)
    norm = Normalization.of(unloaded, plate_basis(plates[0, 0]))
    n_steps = len(plates)
    base = _base_features(unloaded, n_steps, tissue_descriptors(traj), norm)
    origins = norm.to_frame(plates[:, :, ORIGIN])  # (T, 2, 3) mm in the lower plate's frame
    lower, upper = origins[:, 0, 2], origins[:, 1, 2]  # heights along the lower plate's normal
    first_contact = lower + (upper - lower) / (1.0 - compression_ratio)  # upper at CR 0
    code = traj.node_tissue_code
    per_step = np.stack(
        [
            (first_contact - upper) / norm.scale,  # 12: plate travel, normalised
            *norm.apply(plates[:, 0, ORIGIN])[:, 1:].T,  # 13-14: lower edge (y', z')
            *norm.apply(plates[:, 1, ORIGIN])[:, 1:].T,  # 15-16: upper edge (y', z')
        ],
        axis=1,
    )  # (T, 5)
    per_node = np.stack(
        [
            upper_contact(traj, plates),  # 17
            (traj.node_flags & NodeFlag.SKIN) > 0,  # 18
            (code >> 2) & 1,  # 19: gland bit
            (code >> 1) & 1,  # 20: fat bit
            code & 1,  # 21: muscle bit
            np.full(traj.n_nodes, LATERALITY[laterality]),  # 22
        ],
        axis=1,
    ).astype(np.float32)  # (N, 6)
    features = np.concatenate(
        [
            base,
            np.broadcast_to(per_step[:, None, :], (n_steps, traj.n_nodes, 5)),
            np.broadcast_to(per_node[None], (n_steps, traj.n_nodes, 6)),
        ],
        axis=2,
    ).astype(np.float32)
    return features, norm


def compression_features(
    traj: Trajectory,
) -> tuple[NDArray[np.float32], NDArray[np.float32], Normalization]:
    """Compression instances of a simulated breast.

    Returns
    -------
    features : (T2, N, 22) float32
        `COMPRESSION_FEATURES` per step and node.
    targets : (T2, N, 3) float32
        Normalised node coordinates per step, in the lower plate's frame (`compression_inputs`).
    normalization : Normalization
        Of the compression's input geometry (`Trajectory.reference_shape`: the unloaded
        shape, or the imaged one when the unloaded-state step was skipped);
        ``normalization.invert(targets)`` gives patient-frame millimetres.

    Raises
    ------
    ValueError
        The breast has no compression steps, or its metadata no laterality.
    """
    source = traj.source
    if not len(traj.compressed):
        raise ValueError(f"{source}: not simulated (field 'compressed' is empty)")
    features, norm = compression_inputs(
        traj, traj.reference_shape, traj.plates, traj.compression_ratio
    )
    return features, norm.apply(traj.compressed).astype(np.float32), norm
