"""Whole breasts as graphs over their tetrahedral mesh, for the mesh-aware surrogate.

    dm = MeshGraphDataModule("data/cohort/full/trajectories", step="compression")

One item is one breast, not one node: its mesh edges, per-node inputs, the simulation's
conditions (tissue stiffness, friction, view) and per-step inputs (the plates' schedule, or
the load fraction of the unloaded-state step), with the node coordinates of every recorded
step as the target (`graph_sample`). Coordinates are those of the sequence models
(`datamodules.features`: z-scored per breast with equation 1, in the lower plate's frame for
the compression), so the errors in millimetres, the splits (`TrajectoryDataModule.setup`:
by patient, one-fold or k-fold) and the run folders are the same as theirs. Nothing here
depends on the mesh's resolution: a breast remeshed at four times the elements is just a
larger graph.

The per-breast samples are cached as ``<cache_dir>/graph_<step>/P0007_L.graph.npz`` with the
``.json`` of the feature cache (patient, site, node and step counts, normalisation, the
simulation's conditions, the source's stamp), written atomically and rebuilt when the source
changes.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np
import torch
from numpy.typing import NDArray
from torch.utils.data import DataLoader, Dataset

from datamodules.features import LATERALITY, FeatureSchema, Normalization, upper_contact
from datamodules.splits import TISSUES
from datamodules.trajectories import (
    Breast,
    TrajectoryDataModule,
    cache_meta,
    node_offsets,
    recorded_conditions,
)
from fem.contract.atomic import atomic_path
from fem.contract.plates import ORIGIN, plate_basis
from fem.contract.quality import mesh_edges
from fem.contract.trajectory import NodeFlag, Trajectory, read_npz

#: Per-node inputs (both steps): normalised input coordinates in the step's frame, flags,
#: the paper's tissue bits and the laterality.
NODE_FEATURES = (
    "x",
    "y",
    "z",
    "skin",
    "muscle_interface",
    "upper_contact",
    "tissue_bit_2_gland",
    "tissue_bit_1_fat",
    "tissue_bit_0_muscle",
    "laterality",
)

#: Per-step inputs of each simulation step.
STEP_INPUTS = {
    "unloaded": ("load_fraction",),
    "compression": (
        "load_fraction",
        "compression_ratio",
        "upper_plate_travel",
        "lower_plate_edge_y",
        "lower_plate_edge_z",
        "upper_plate_edge_y",
        "upper_plate_edge_z",
    ),
}

#: Per-node, per-step inputs of each simulation step: where a node's input position lies
#: against the plates at that step (normalised heights along the lower plate's normal).
NODE_STEP_INPUTS = {
    "unloaded": (),
    "compression": ("height_above_lower_plate", "depth_below_upper_plate"),
}

#: The paper cohort's Young's moduli (Pa) of the `TISSUES`: the stiffness inputs are log-ratios
#: to them.
REFERENCE_YOUNG = MappingProxyType(
    dict(zip(TISSUES, (1100.0, 2500.0, 6000.0, 1000.0), strict=True))
)

#: Per-breast inputs: the simulation's conditions (`Conditions.vector`).
CONDITION_FEATURES = (*(f"log_young_{t}" for t in TISSUES), "friction", "mlo", "plate_angle_rad")


def graph_inputs(step: str) -> tuple[str, ...]:
    """Every input of the graph model of ``step``, in the order of its schema."""
    return (*NODE_FEATURES, *STEP_INPUTS[step], *NODE_STEP_INPUTS[step], *CONDITION_FEATURES)


@dataclass(frozen=True)
class Conditions:
    """What a simulation is run under, as the surrogate sees it.

    Attributes
    ----------
    young : Mapping[str, float]
        Young's modulus per tissue (fat, gland, muscle, skin), Pa.
    friction : float
        Coulomb friction coefficient between skin and plates.
    view : {"cc", "mlo"}
        Cranio-caudal or mediolateral-oblique plates.
    angle : float
        The oblique plates' angle, degrees (ignored for ``cc``).
    """

    young: Mapping[str, float]
    friction: float
    view: str
    angle: float = 45.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "young", MappingProxyType(dict(self.young)))  # a copy, read-only
        missing = set(REFERENCE_YOUNG) - set(self.young)
        if missing:
            raise ValueError(f"conditions.young: no modulus for {sorted(missing)}")
        for tissue, e in self.young.items():
            if not (isinstance(e, int | float) and np.isfinite(e) and e > 0):
                raise ValueError(f"conditions.young.{tissue} must be a positive number, got {e!r}")
        if not (isinstance(self.friction, int | float) and 0 <= self.friction < np.inf):
            raise ValueError(f"conditions.friction must be >= 0, got {self.friction!r}")
        if self.view not in ("cc", "mlo"):
            raise ValueError(f"conditions.view must be 'cc' or 'mlo', got {self.view!r}")
        if not (isinstance(self.angle, int | float) and 0 < self.angle < 90):
            raise ValueError(f"conditions.angle must be in (0, 90) degrees, got {self.angle!r}")

    @classmethod
    def of_metadata(cls, metadata: Mapping, source: str = "trajectory") -> Conditions:
        """The conditions a trajectory was simulated under (``metadata["simulation"]``).

        Raises
        ------
        ValueError
            The metadata lack the simulation's settings; the message names the source and
            the field.
        """
        return cls.of_recorded(recorded_conditions(metadata), source)

    @classmethod
    def of_recorded(cls, raw: Mapping | None, source: str = "trajectory") -> Conditions:
        """The conditions of `datamodules.trajectories.recorded_conditions`'s plain values
        (None: not recorded), as `of_metadata` (its errors)."""
        if raw is None:
            raise ValueError(
                f"{source}: metadata field 'simulation' must hold materials (young of "
                f"{', '.join(TISSUES)}), friction, view and angle"
            )
        young = {t: raw[f"young_{t}"] for t in TISSUES}
        try:
            return cls(young, raw["friction"], raw["view"], raw["angle"])
        except ValueError as exc:
            raise ValueError(f"{source}: metadata field 'simulation': {exc}") from exc

    def __str__(self) -> str:
        """E.g. ``fat 1100 Pa, gland 2500 Pa, muscle 6000 Pa, skin 1000 Pa, friction 0.25, cc``."""
        young = ", ".join(f"{t} {e:g} Pa" for t, e in self.young.items())
        view = f"mlo at {self.angle:g} deg" if self.view == "mlo" else self.view
        return f"{young}, friction {self.friction:g}, {view}"

    def vector(self) -> NDArray[np.float32]:
        """`CONDITION_FEATURES`, shape (7,)."""
        mlo = float(self.view == "mlo")
        return np.array(
            [
                *(np.log(self.young[t] / e) for t, e in REFERENCE_YOUNG.items()),
                self.friction,
                mlo,
                mlo * np.deg2rad(self.angle),
            ],
            np.float32,
        )


#: The paper cohort's conditions (`conf/simulation/default.yaml`): the models of the paper know
#: only these.
PAPER_CONDITIONS = Conditions(REFERENCE_YOUNG, 0.25, "cc", 45.0)


def stiffness_bounds(breasts: Sequence[Breast]) -> torch.Tensor:
    """The range (2, C) of the breasts' conditions (`CONDITION_FEATURES`) over their
    stiffness inputs (the ``log_young_*`` columns): lowest and highest; infinite for the
    other conditions (friction, view, angle), which are not bounded.

    Raises
    ------
    ValueError
        No breasts, or one whose trajectory does not record its conditions.
    """
    if not breasts:
        raise ValueError("stiffness_bounds: no breasts")
    vectors = np.stack(
        [Conditions.of_recorded(b.conditions(), str(b.stem)).vector() for b in breasts]
    )  # (B, C)
    bounds = torch.tensor([-np.inf, np.inf])[:, None].repeat(1, len(CONDITION_FEATURES))
    stiff = [i for i, name in enumerate(CONDITION_FEATURES) if name.startswith("log_young_")]
    bounds[0, stiff] = torch.from_numpy(vectors[:, stiff].min(axis=0))
    bounds[1, stiff] = torch.from_numpy(vectors[:, stiff].max(axis=0))
    return bounds  # (2, C)


def node_inputs(
    traj: Trajectory, geometry: NDArray, norm: Normalization, upper: NDArray
) -> NDArray:
    """`NODE_FEATURES` of every node, (N, 10) float32; ``upper`` the upper-contact flags (N,)."""
    laterality = traj.metadata.get("laterality")
    if laterality not in LATERALITY:
        raise ValueError(
            f"{traj.source}: metadata field 'laterality' must be 'L' or 'R', got {laterality!r}"
        )
    code = traj.node_tissue_code
    flags = traj.node_flags
    return np.column_stack(
        [
            norm.apply(geometry),
            (flags & NodeFlag.SKIN) > 0,
            (flags & NodeFlag.MUSCLE_INTERFACE) > 0,
            upper,
            (code >> 2) & 1,
            (code >> 1) & 1,
            code & 1,
            np.full(traj.n_nodes, LATERALITY[laterality]),
        ]
    ).astype(np.float32)


def unloaded_graph_inputs(
    traj: Trajectory, n_steps: int, conditions: Conditions, edges: NDArray | None = None
) -> tuple[dict[str, NDArray], Normalization]:
    """The unloaded-state step's graph inputs of a breast mesh, simulated or not (``edges``:
    its `mesh_edges`, computed when not given).

    Returns
    -------
    sample : dict
        ``nodes`` (N, 10), ``edges`` (2, 2M), ``steps`` (T, 1), ``node_steps`` (T, N, 0),
        ``conditions`` (7,).
    normalization : Normalization
        Of the imaged geometry (equation 1).
    """
    norm = Normalization.of(traj.points)
    upper = (traj.node_flags & NodeFlag.UPPER_CONTACT) > 0
    sample = {
        "nodes": node_inputs(traj, traj.points, norm, upper),
        "edges": mesh_edges(traj.cells) if edges is None else edges,
        "steps": (np.arange(1, n_steps + 1, dtype=np.float32) / n_steps)[:, None],
        "node_steps": np.zeros((n_steps, traj.n_nodes, 0), np.float32),
        "conditions": conditions.vector(),
    }
    return sample, norm


def compression_graph_inputs(
    traj: Trajectory,
    reference: NDArray,
    plates: NDArray,
    compression_ratio: NDArray,
    conditions: Conditions,
    edges: NDArray | None = None,
) -> tuple[dict[str, NDArray], Normalization]:
    """The compression step's graph inputs of a breast mesh from its unloaded shape and the
    plates' schedule (simulated, or placed by `fem.engine.boundary.plate_schedule`).

    Parameters
    ----------
    traj : Trajectory
        The mesh: cells, tissues, node flags, laterality.
    reference : (N, 3)
        The compression's input geometry, mm.
    plates : (T, 2, 3, 3)
        Lower and upper plate frames per recorded step, mm (`fem.contract.plates`).
    compression_ratio : (T,)
        Per recorded step.
    conditions : Conditions
        Stiffness, friction, view.
    edges : (2, 2M) int, optional
        The mesh's `mesh_edges`, computed when not given.

    Returns
    -------
    sample : dict
        ``nodes`` (N, 10), ``edges`` (2, 2M), ``steps`` (T, 7), ``node_steps`` (T, N, 2),
        ``conditions`` (7,); coordinates in the lower plate's frame, normalised.
    normalization : Normalization
        Of ``reference`` in the lower plate's frame.
    """
    plates = np.asarray(plates, np.float64)
    n_steps = len(plates)
    norm = Normalization.of(reference, plate_basis(plates[0, 0]))
    nodes = node_inputs(traj, reference, norm, upper_contact(traj, plates))
    lower = norm.apply(plates[:, 0, ORIGIN])  # (T, 3) normalised, lower plate's frame
    upper = norm.apply(plates[:, 1, ORIGIN])
    first_contact = lower[:, 2] + (upper[:, 2] - lower[:, 2]) / (1.0 - compression_ratio)
    steps = np.column_stack(
        [
            np.arange(1, n_steps + 1) / n_steps,
            compression_ratio,
            first_contact - upper[:, 2],
            lower[:, 1:],
            upper[:, 1:],
        ]
    ).astype(np.float32)
    z = nodes[:, 2]
    node_steps = np.stack([z[None] - lower[:, 2:3], upper[:, 2:3] - z[None]], axis=-1)
    sample = {
        "nodes": nodes,
        "edges": mesh_edges(traj.cells) if edges is None else edges,
        "steps": steps,
        "node_steps": node_steps.astype(np.float32),
        "conditions": conditions.vector(),
    }
    return sample, norm


def blank_sample(step: str, n_steps: int) -> dict[str, NDArray]:
    """The inputs of one tetrahedron with zero features: a model's first call (its kernels
    built) without a breast."""
    return {
        "nodes": np.zeros((4, len(NODE_FEATURES)), np.float32),
        "edges": mesh_edges(np.arange(4)[None]),
        "steps": np.zeros((n_steps, len(STEP_INPUTS[step])), np.float32),
        "node_steps": np.zeros((n_steps, 4, len(NODE_STEP_INPUTS[step])), np.float32),
        "conditions": np.zeros(len(CONDITION_FEATURES), np.float32),
    }


def graph_sample(traj: Trajectory, step: str) -> tuple[dict[str, NDArray], Normalization]:
    """A simulated breast as one training item of ``step``: the inputs of
    `unloaded_graph_inputs` / `compression_graph_inputs` and ``targets`` (T, N, 3), the
    normalised node coordinates per recorded step.

    Raises
    ------
    ValueError
        The step was not simulated, or the metadata lack the laterality or the conditions.
    """
    conditions = Conditions.of_metadata(traj.metadata, traj.source)
    if step == "unloaded":
        if not len(traj.unloaded):
            raise ValueError(f"{traj.source}: not simulated (field 'unloaded' is empty)")
        sample, norm = unloaded_graph_inputs(traj, len(traj.unloaded), conditions)
        positions = traj.unloaded
    else:
        if not len(traj.compressed):
            raise ValueError(f"{traj.source}: not simulated (field 'compressed' is empty)")
        sample, norm = compression_graph_inputs(
            traj, traj.reference_shape, traj.plates, traj.compression_ratio, conditions
        )
        positions = traj.compressed
    sample["targets"] = norm.apply(positions).astype(np.float32)
    return sample, norm


def cache_graph(source: Path, stem: Path, step: str) -> None:
    """Write one simulated breast's graph sample (atomically; the ``.json`` last, so a sample
    without it is not finished)."""
    traj = Trajectory.load(source)
    traj.metadata.setdefault("source", str(source))
    sample, norm = graph_sample(traj, step)
    with atomic_path(stem.with_suffix(".graph.npz")) as tmp, open(tmp, "wb") as f:
        np.savez(f, **sample)
    with atomic_path(stem.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(cache_meta(traj, source, norm, len(sample["targets"]))))


@dataclass(frozen=True)
class GraphBreast(Breast):
    """One cached breast graph; `features` is its whole sample (a mapping of arrays)."""

    def features(self) -> dict[str, NDArray]:  # type: ignore[override]
        """The sample of `graph_sample` (``targets`` included), read from the cache."""
        return read_npz(self.stem.with_suffix(".graph.npz"), "a graph sample (.graph.npz)")

    def targets(self) -> NDArray[np.float32]:
        """(N, T, 3) normalised coordinates, the node-major layout of the sequence caches."""
        return self.features()["targets"].transpose(1, 0, 2)


def batch_graphs(samples: list[dict[str, NDArray]]) -> dict[str, torch.Tensor]:
    """Several breasts as one disconnected graph.

    Returns
    -------
    dict
        ``nodes`` (N, Fn) and ``node_steps`` (T, N, Fns) concatenated over the breasts,
        ``edges`` (2, E) offset to the concatenated nodes, ``graph`` (N,) each node's breast
        in the batch, ``steps`` (B, T, Fs), ``conditions`` (B, C) and, when the samples have
        them, ``targets`` (T, N, 3).

    Raises
    ------
    ValueError
        The breasts have different numbers of recorded steps.
    """
    lengths = {len(s["steps"]) for s in samples}
    if len(lengths) > 1:
        raise ValueError(f"breasts of one batch must share the step count, got {sorted(lengths)}")
    sizes = [len(s["nodes"]) for s in samples]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    out = {
        "nodes": np.concatenate([s["nodes"] for s in samples]),
        "edges": np.concatenate([s["edges"] + o for s, o in zip(samples, offsets, strict=True)], 1),
        "graph": np.repeat(np.arange(len(samples)), sizes),
        "steps": np.stack([s["steps"] for s in samples]),
        "node_steps": np.concatenate([s["node_steps"] for s in samples], axis=1),
        "conditions": np.stack([s["conditions"] for s in samples]),
    }
    if all("targets" in s for s in samples):
        out["targets"] = np.concatenate([s["targets"] for s in samples], axis=1)
    return {k: torch.as_tensor(np.asarray(v)) for k, v in out.items()}


class BreastGraphs(Dataset):
    """One item per breast: its sample, index, normalisation scale (mm per unit) and the
    dataset index of its first node (for `mammo_net.metrics.BreastErrors`). Samples are read
    once and kept (a 600-node compression sample is about 1 MB)."""

    def __init__(self, breasts: list[GraphBreast]) -> None:
        self.breasts = breasts
        self.offsets, self.scales = node_offsets(breasts)
        self._samples: dict[int, dict[str, NDArray]] = {}

    def __len__(self) -> int:
        return len(self.breasts)

    def __getitem__(self, index: int) -> tuple[dict[str, NDArray], int, float, int]:
        if index not in self._samples:
            self._samples[index] = self.breasts[index].features()
        return self._samples[index], index, float(self.scales[index]), int(self.offsets[index])


def collate_graphs(items: list[tuple[dict[str, NDArray], int, float, int]]) -> dict:
    """`batch_graphs` of the items, with each node's breast index, scale and dataset index."""
    samples, index, scale, first = zip(*items, strict=True)
    batch = batch_graphs(list(samples))
    sizes = [len(s["nodes"]) for s in samples]
    batch["breast"] = torch.as_tensor(np.repeat(index, sizes))
    batch["scale"] = torch.as_tensor(np.repeat(np.asarray(scale, np.float32), sizes))
    batch["node"] = torch.as_tensor(
        np.concatenate([f + np.arange(n) for f, n in zip(first, sizes, strict=True)])
    )
    return batch


class MeshGraphDataModule(TrajectoryDataModule):
    """Whole-breast graphs of one simulation step, split by patient exactly as
    `TrajectoryDataModule` splits (same arguments; ``batch_size`` counts breasts).

    The caches lie where the sequence caches do (``<data_dir>/cache`` by default), in the
    folder ``graph_<step>`` beside theirs.
    """

    cache_last = ".json"
    breast_type = GraphBreast

    def __init__(self, *args, batch_size: int = 4, **kwargs) -> None:
        super().__init__(*args, batch_size=batch_size, **kwargs)

    @property
    def cache_kind(self) -> str:
        return f"graph_{self.hparams.step}"

    def write_cache(self, source: Path, stem: Path) -> None:
        """Cache one breast's graph (`cache_graph`)."""
        cache_graph(source, stem, self.hparams.step)

    def schema(self) -> FeatureSchema:
        """The inputs of graph models trained here (`graph_inputs`), with the longest
        trajectory's step count."""
        return FeatureSchema.current(
            self.hparams.step, graph_inputs(self.hparams.step), self.max_steps()
        )

    def _loader(self, breasts: list[GraphBreast], shuffle: bool) -> DataLoader:
        return DataLoader(
            BreastGraphs(breasts),
            batch_size=self.hparams.batch_size,
            shuffle=shuffle,
            num_workers=self.hparams.num_workers,
            collate_fn=collate_graphs,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val, shuffle=False)
