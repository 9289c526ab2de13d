"""Per-node, per-step features of the reference paper (section 2.2) and its normalisation (eq. 1).

One instance is one node at one recorded step. The unloaded-state model sees 11 features, the
compression model 22 (`UNLOADED_FEATURES`, `COMPRESSION_FEATURES`; units and definitions in
docs/features.md); the targets are the node's coordinates at that step. Coordinates, plate
positions and targets are z-scored per breast (equation 1): ``(v - mu) / sigma`` with ``mu``
the mean node position of the step's input geometry and ``sigma`` the root-mean-square
distance of its nodes from ``mu`` (one scale for all three axes, so shapes are not distorted);
`Normalization` keeps both to map predictions back to millimetres.

The input geometry of the unloaded-state step is the imaged mesh (``points``); that of the
compression step is the unloaded shape (``unloaded[-1]``), the compression's stress-free
reference, so a predicted unloaded state can feed the compression model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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


@dataclass(frozen=True)
class FeatureSchema:
    """What a trained model takes: its simulation step, its features in order and the number
    of recorded steps it was trained on (the trees see the step index as feature 4). Every
    model file stores it, so a model is never fed features it was not trained on."""

    step: str
    features: tuple[str, ...]
    n_steps: int

    @classmethod
    def of(cls, step: str, n_steps: int) -> FeatureSchema:
        """This code's schema of ``step`` with ``n_steps`` recorded steps."""
        if step not in STEP_FEATURES:
            raise ValueError(f"step must be one of {sorted(STEP_FEATURES)}, got {step!r}")
        return cls(step, STEP_FEATURES[step], int(n_steps))

    def to_json(self) -> str:
        return json.dumps(
            {"step": self.step, "features": list(self.features), "n_steps": self.n_steps}
        )

    @classmethod
    def from_json(cls, text: str, source: str = "model") -> FeatureSchema:
        try:
            d = json.loads(text)
            return cls(str(d["step"]), tuple(str(f) for f in d["features"]), int(d["n_steps"]))
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{source}: unreadable feature schema {text!r}: {exc}") from exc

    def check(self, step: str, source: str = "model") -> None:
        """Refuse a model trained for another step or on other features than this code's."""
        if step != self.step:
            raise ValueError(
                f"{source}: the model predicts the {self.step} step, not the {step} step"
            )
        expected = STEP_FEATURES.get(step)
        if self.features != expected:
            raise ValueError(
                f"{source}: the model was trained on the features {list(self.features)}, this "
                f"version computes {list(expected or ())} for the {step} step; retrain it"
            )


@dataclass(frozen=True)
class Normalization:
    """Per-breast z-score of coordinates (equation 1): ``(v - mean) / scale``.

    Attributes
    ----------
    mean : (3,) float64
        Mean node position of the input geometry, mm.
    scale : float
        Root-mean-square distance of the nodes from ``mean``, mm.
    """

    mean: NDArray
    scale: float

    @classmethod
    def of(cls, points: NDArray) -> Normalization:
        """The normalisation of a geometry ``points`` (N, 3), mm."""
        mean = points.mean(axis=0)
        return cls(mean, float(np.sqrt(((points - mean) ** 2).sum(axis=1).mean())))

    def apply(self, v: NDArray, axes: slice | list[int] = slice(None)) -> NDArray:
        """Normalise coordinates ``v`` (..., k) whose last axis holds the axes ``axes``."""
        return (v - self.mean[axes]) / self.scale

    def invert(self, v: NDArray, axes: slice | list[int] = slice(None)) -> NDArray:
        """Millimetres of normalised coordinates ``v`` (..., k)."""
        return v * self.scale + self.mean[axes]


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


def compression_inputs(
    traj: Trajectory, unloaded: NDArray, plates: NDArray, compression_ratio: NDArray
) -> tuple[NDArray[np.float32], Normalization]:
    """Compression features of a breast mesh from its unloaded shape and the plates' schedule
    (simulated, or predicted and placed by `fem.engine.simulation.plate_schedule`).

    Parameters
    ----------
    traj : Trajectory
        The mesh: cells, tissues, node flags and ``metadata["laterality"]``.
    unloaded : (N, 3)
        The unloaded shape, the compression's input geometry, mm.
    plates : (T, 2, 2)
        (y, z) of the lower and upper plate's chest-side edge per recorded step, mm.
    compression_ratio : (T,)
        Compression ratio per recorded step.

    Returns
    -------
    features : (T, N, 22) float32
        `COMPRESSION_FEATURES` per recorded step and node.
    normalization : Normalization
        Of the unloaded shape.

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
    norm = Normalization.of(unloaded)
    n_steps = len(plates)
    base = _base_features(unloaded, n_steps, tissue_descriptors(traj), norm)
    lower, upper = plates[:, 0, 1], plates[:, 1, 1]
    first_contact = lower + (upper - lower) / (1.0 - compression_ratio)  # upper at CR 0
    code = traj.node_tissue_code
    per_step = np.stack(
        [
            (first_contact - upper) / norm.scale,  # 12: plate travel, normalised
            *norm.apply(plates[:, 0], [1, 2]).T,  # 13-14: lower edge (y, z)
            *norm.apply(plates[:, 1], [1, 2]).T,  # 15-16: upper edge (y, z)
        ],
        axis=1,
    )  # (T, 5)
    per_node = np.stack(
        [
            (traj.node_flags & NodeFlag.UPPER_CONTACT) > 0,  # 17
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
        Normalised node coordinates per step.
    normalization : Normalization
        Of the unloaded shape (the compression's input geometry).

    Raises
    ------
    ValueError
        The breast has no unloaded state, or its metadata no laterality.
    """
    source = traj.source
    if not len(traj.unloaded) or not len(traj.compressed):
        raise ValueError(f"{source}: not simulated (fields 'unloaded'/'compressed' are empty)")
    features, norm = compression_inputs(
        traj, traj.unloaded[-1], traj.plates, traj.compression_ratio
    )
    return features, norm.apply(traj.compressed).astype(np.float32), norm
