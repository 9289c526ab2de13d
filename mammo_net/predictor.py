"""Deformed shapes of a new breast from the surrogates, without the FE: the Python API for
registration loops.

    unloaded = load_surrogate("outputs/cv/att_blstm/unloaded/fold0/checkpoints/last.ckpt")
    compression = load_surrogate("outputs/.../baselines/xgboost.json")
    shapes = predict_breast(traj, unloaded, compression, thicknesses=[45.0, 50.0, 55.0])
    shapes.compressed  # (K, T2, N, 3) mm: every recorded step for each thickness

The unloaded-state model maps the imaged mesh to the unloaded shape; the plates are placed on
that shape as the FE places them (`fem.simulate.plate_schedule`) for each compressed thickness,
and the compression model maps the shape and plates to every recorded compression step. All
thicknesses go through the compression model in one batched call.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datamodules.features import FeatureSchema, compression_inputs, unloaded_inputs
from fem.simulate import plate_schedule
from fem.trajectory import Trajectory
from mammo_net import baselines
from mammo_net.inference import network_predictor, rows_predictor

MODEL_SUFFIXES = (".ckpt", ".json", ".ubj", ".npz")


@dataclass(frozen=True)
class Surrogate:
    """A trained model of one simulation step: ``predict`` maps features (N, T, F) to
    normalised coordinates (N, T, 3); ``schema`` says which features and steps it takes."""

    name: str
    schema: FeatureSchema
    predict: Callable[[NDArray], NDArray[np.float32]]


def load_surrogate(path: str | Path, step: str | None = None) -> Surrogate:
    """Load a model file without executing code from it: a Lightning checkpoint (``.ckpt``,
    ``weights_only``), XGBoost JSON/UBJSON (``.json``/``.ubj``) or the forest's arrays
    (``.npz``).

    Raises
    ------
    ValueError
        Unknown suffix, no feature schema in the file, or a schema that is not ``step``'s or
        not this version's features.
    """
    path = Path(path)
    if path.suffix == ".ckpt":
        from mammo_net.module import SurrogateModule

        model = SurrogateModule.load_from_checkpoint(path, map_location="cpu", weights_only=True)
        name, schema, predict = "att_blstm", model.schema, network_predictor(model)
    elif path.suffix in (".json", ".ubj"):
        booster = baselines.load_xgboost(path)
        name, schema = "xgboost", baselines.xgboost_schema(booster, str(path))
        predict = rows_predictor(lambda X: baselines.predict_xgboost(booster, X))
    elif path.suffix == ".npz":
        forest = baselines.load_forest(path)
        name, schema = "ert", baselines.forest_schema(path)
        predict = rows_predictor(forest.predict)
    else:
        raise ValueError(f"{path}: a model file ends in one of {MODEL_SUFFIXES}")
    if schema is None:
        raise ValueError(f"{path}: the file has no feature schema; retrain the model")
    schema.check(step or schema.step, str(path))
    return Surrogate(name, schema, predict)


@dataclass
class BreastShapes:
    """Predicted node positions of one breast, mm.

    Attributes
    ----------
    unloaded : (T1, N, 3)
        Every recorded step of the unloaded-state estimate (the last one is the unloaded shape).
    compressed : (K, T2, N, 3)
        Every recorded compression step, for each of the K requested thicknesses.
    plates : (K, T2, 2, 2)
        (y, z) of the lower and upper plate's chest-side edge per step, mm.
    compression_ratio : (K, T2)
        Compression ratio per step.
    thickness : (K,)
        The compressed thicknesses, mm.
    """

    unloaded: NDArray[np.float32]
    compressed: NDArray[np.float32]
    plates: NDArray[np.float64]
    compression_ratio: NDArray[np.float64]
    thickness: NDArray[np.float64]


def predict_breast(
    traj: Trajectory,
    unloaded: Surrogate | None,
    compression: Surrogate,
    thicknesses: Sequence[float],
) -> BreastShapes:
    """The unloaded state and the compression of ``traj``'s mesh to each thickness (mm).

    ``unloaded=None`` takes the unloaded shape from ``traj.unloaded`` (an FE result) instead.

    Raises
    ------
    ValueError
        A thickness is not below the unloaded breast's cranio-caudal extent, or models of the
        wrong step.
    """
    source = str(traj.metadata.get("source", "mesh"))
    compression.schema.check("compression", f"{source}: compression model {compression.name}")
    if unloaded is None:
        if not len(traj.unloaded):
            raise ValueError(f"{source}: no unloaded-state model and no FE 'unloaded' field")
        steps = traj.unloaded.astype(np.float32)
    else:
        unloaded.schema.check("unloaded", f"{source}: unloaded-state model {unloaded.name}")
        features, norm = unloaded_inputs(traj, unloaded.schema.n_steps)  # (T1, N, 11)
        steps = norm.invert(unloaded.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    shape = steps[-1].astype(np.float64)
    n_steps = compression.schema.n_steps
    schedules = [plate_schedule(traj, shape, float(t)).recorded(n_steps) for t in thicknesses]
    plates = np.stack([p for p, _ in schedules])  # (K, T2, 2, 2)
    ratio = np.stack([r for _, r in schedules])  # (K, T2)
    batch = []
    for k in range(len(schedules)):  # the same shape, so the same normalisation, for every k
        features, norm = compression_inputs(traj, shape, plates[k], ratio[k])  # (T2, N, 22)
        batch.append(features.transpose(1, 0, 2))
    out = norm.invert(compression.predict(np.concatenate(batch)))  # (K N, T2, 3), one call
    compressed = out.reshape(len(batch), traj.n_nodes, n_steps, 3).transpose(0, 2, 1, 3)
    return BreastShapes(
        steps.astype(np.float32),
        compressed.astype(np.float32),
        plates,
        ratio,
        np.asarray(thicknesses, float),
    )
