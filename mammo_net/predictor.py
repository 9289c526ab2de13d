"""Deformed shapes of a new breast from the surrogates, without the FE: the Python API for
registration loops.

    unloaded = load_surrogate("outputs/cv/att_blstm/unloaded/fold0/checkpoints/last.ckpt")
    compression = load_surrogate("outputs/.../baselines/xgboost.json")
    shapes = predict_breast(traj, unloaded, compression, thicknesses=[45.0, 50.0, 55.0])
    shapes.compressed  # (K, T2, N, 3) mm: every recorded step for each thickness

The unloaded-state model maps the imaged mesh to the unloaded shape; the plates are placed on
that shape as the FE places them (`fem.engine.boundary.plate_schedule`) for each compressed thickness,
and the compression model maps the shape and plates to every recorded compression step. All
thicknesses go through the compression model in one batched call.
"""

from __future__ import annotations

import csv
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import meshio
import numpy as np
from numpy.typing import NDArray

from datamodules.features import STEP_FEATURES, FeatureSchema, compression_inputs, unloaded_inputs
from datamodules.graphs import (
    PAPER_CONDITIONS,
    Conditions,
    MeshGraphDataModule,
    blank_sample,
    compression_graph_inputs,
    graph_inputs,
    unloaded_graph_inputs,
)
from datamodules.trajectories import TrajectoryDataModule
from fem.breasts.figures import shapes_sections_png
from fem.breasts.io import write_mesh
from fem.contract.atomic import atomic_path
from fem.contract.landmarks import SOURCE_TO_IMAGE_MM, carry, locate, project_cc
from fem.contract.plates import ORIGIN
from fem.contract.quality import mesh_edges
from fem.contract.timeseries import write_time_series
from fem.contract.trajectory import Trajectory, reading_file
from fem.engine.boundary import plate_schedule
from mammo_net import baselines
from mammo_net.inference import save_predictions
from mammo_net.sequence_trees import from_forest, from_xgboost, sequence_predictor

MODEL_SUFFIXES = (".ckpt", ".json", ".ubj", ".npz")


@dataclass(frozen=True)
class Surrogate:
    """A trained model of one simulation step: ``predict`` maps features (N, T, F), or with
    ``graph`` a breast's graph sample (`datamodules.graphs`), to normalised coordinates
    (N, T, 3); ``schema`` says which inputs and steps it takes."""

    name: str
    schema: FeatureSchema
    predict: Callable[[Any], NDArray[np.float32]]
    graph: bool = False

    def inputs(self, step: str) -> tuple[str, ...]:
        """The inputs this code computes for the model's kind and ``step``."""
        return graph_inputs(step) if self.graph else STEP_FEATURES[step]

    def check(self, step: str, source: str) -> None:
        """Refuse a model of another step or of other inputs (`FeatureSchema.check`)."""
        if step not in STEP_FEATURES:
            raise ValueError(f"{source}: step must be one of {sorted(STEP_FEATURES)}, got {step!r}")
        self.schema.check(step, source, self.inputs(step))


def load_surrogate(
    path: str | Path, step: str | None = None, row_by_row: bool = False, precision: str = "32-true"
) -> Surrogate:
    """Load a model file without executing code from it: a Lightning checkpoint (``.ckpt``,
    `mammo_net.module.SurrogateModule.from_checkpoint`), XGBoost JSON/UBJSON
    (``.json``/``.ubj``) or the forest's arrays (``.npz``). The trees predict whole node
    sequences by step intervals (`mammo_net.sequence_trees`); ``row_by_row`` uses their own
    row-by-row predictions instead (the same values, slower; for benchmarks). ``precision``
    of the network: ``"32-true"`` or ``"bf16-mixed"`` (`mammo_net.inference.network_predictor`).

    Raises
    ------
    ValueError
        Unknown suffix, no feature schema in the file, or a schema that is not ``step``'s or
        not this version's features.
    """
    path = Path(path)
    graph = False
    if path.suffix == ".ckpt":
        from mammo_net.module import NetworkModule

        model = NetworkModule.from_checkpoint(path)
        name, schema, graph = model.name, model.schema, model.takes_graphs
        predict = model.predictor(precision)
    elif path.suffix in (".json", ".ubj"):
        booster = baselines.load_xgboost(path)
        name, schema = "xgboost", baselines.xgboost_schema(booster, str(path))
        rows = functools.partial(baselines.predict_xgboost, booster)
        predict = sequence_predictor(None if row_by_row else from_xgboost(booster), rows)
    elif path.suffix == ".npz":
        name, schema = "ert", baselines.forest_schema(path)
        forest = baselines.load_forest(path)
        rows = forest.compiled(len(schema.features)) if schema else None
        predict = sequence_predictor(None if row_by_row else from_forest(forest), rows)
    else:
        raise ValueError(f"{path}: a model file ends in one of {MODEL_SUFFIXES}")
    if schema is None:
        raise ValueError(f"{path}: the file has no feature schema; retrain the model")
    surrogate = Surrogate(name, schema, predict, graph)
    surrogate.check(step or schema.step, str(path))
    # one node (one tetrahedron) through the model: compiled kernels (numba, torch) are built
    # here, not inside the first timed prediction
    if graph:
        predict(blank_sample(schema.step, schema.n_steps))
    else:
        predict(np.zeros((1, schema.n_steps, len(schema.features)), np.float32))
    return surrogate


@dataclass
class BreastShapes:
    """Predicted node positions of one breast, mm.

    Attributes
    ----------
    unloaded : (T1, N, 3)
        Every recorded step of the unloaded-state estimate (the last one is the unloaded shape).
    compressed : (K, T2, N, 3)
        Every recorded compression step, for each of the K requested thicknesses.
    plates : (K, T2, 2, 3, 3)
        Frames (origin, normal, axis) of the lower and upper plate per step
        (`fem.contract.plates`), mm.
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
    conditions: Conditions = PAPER_CONDITIONS,
) -> BreastShapes:
    """The unloaded state and the compression of ``traj``'s mesh to each thickness (mm).

    ``unloaded=None`` takes the unloaded shape from ``traj.unloaded`` (an FE result) instead.
    ``conditions`` (tissue stiffness, friction, view and plate angle) are inputs of graph
    models; the plates are placed in their view. The paper's models know only the paper's
    cc conditions and refuse others.

    Raises
    ------
    ValueError
        A thickness is not below the unloaded breast's cranio-caudal extent, or models of the
        wrong step.
    """
    source = traj.source
    compression.check("compression", f"{source}: compression model {compression.name}")
    for model in (unloaded, compression):
        if model is not None and not model.graph and conditions != PAPER_CONDITIONS:
            raise ValueError(
                f"{source}: the {model.name} model was trained on the paper's conditions only "
                f"({PAPER_CONDITIONS}); other stiffness, friction or views need a graph model"
            )
    edges = mesh_edges(traj.cells)  # of both steps' graphs
    if unloaded is None:
        if not len(traj.unloaded):
            raise ValueError(f"{source}: no unloaded-state model and no FE 'unloaded' field")
        steps = traj.unloaded.astype(np.float32)
    else:
        unloaded.check("unloaded", f"{source}: unloaded-state model {unloaded.name}")
        if unloaded.graph:
            sample, norm = unloaded_graph_inputs(traj, unloaded.schema.n_steps, conditions, edges)
            steps = norm.invert(unloaded.predict(sample)).transpose(1, 0, 2)
        else:
            features, norm = unloaded_inputs(traj, unloaded.schema.n_steps)  # (T1, N, 11)
            steps = norm.invert(unloaded.predict(features.transpose(1, 0, 2))).transpose(1, 0, 2)
    shape = steps[-1].astype(np.float64)
    n_steps = compression.schema.n_steps
    schedules = [
        plate_schedule(traj, shape, float(t), conditions.view, conditions.angle).recorded(n_steps)
        for t in thicknesses
    ]
    plates = np.stack([p for p, _ in schedules])  # (K, T2, 2, 3, 3)
    ratio = np.stack([r for _, r in schedules])  # (K, T2)
    if compression.graph:  # the K thicknesses as one batch of K graphs, one pass
        inputs = [
            compression_graph_inputs(traj, shape, plates[k], ratio[k], conditions, edges)
            for k in range(len(schedules))
        ]
        norms = [norm for _, norm in inputs]
        out = compression.predict([sample for sample, _ in inputs])  # K x (N, T2, 3)
    else:
        batch, norms = [], []
        for k in range(len(schedules)):
            features, norm = compression_inputs(traj, shape, plates[k], ratio[k])  # (T2, N, 22)
            batch.append(features.transpose(1, 0, 2))
            norms.append(norm)  # each in its lower plate's frame
        out = compression.predict(np.concatenate(batch))  # (K N, T2, 3), one call
        out = out.reshape(len(batch), traj.n_nodes, n_steps, 3)
    compressed = np.stack([n.invert(o) for n, o in zip(norms, out, strict=True)])
    compressed = compressed.transpose(0, 2, 1, 3)
    return BreastShapes(
        steps.astype(np.float32),
        compressed.astype(np.float32),
        plates,
        ratio,
        np.asarray(thicknesses, float),
    )


# --- run folders ---------------------------------------------------------------------------

#: The model files of a train.py run folder that `predict_run` predicts with (the network's
#: checkpoint is an Att-BLSTM's or a graph model's: its own file says which).
RUN_MODELS = {
    "network": "checkpoints/best.ckpt",
    "xgboost": "baselines/xgboost.json",
    "ert": "baselines/ert.npz",
}


def predict_run(run: str | Path) -> list[Path]:
    """Write the missing ``predictions/<model>.npz`` of a run folder from its model files
    (`RUN_MODELS`): the validation breasts of the run's split, read from its
    ``.hydra/config.yaml`` (`datamodules.trajectories.TrajectoryDataModule.from_run`, or the
    graph data module's for a graph model: plain values, nothing instantiated). A run kept as
    model files (the committed cross-validation folds in ``results/``) thus feeds the
    evaluation report without retraining. A prediction's existing timing file
    (``predictions/<model>.json``, committed beside the model files) is kept: it records the
    run's own measurement, not this machine's."""
    run = Path(run)
    todo = [
        run / file
        for key, file in RUN_MODELS.items()
        if (run / file).exists() and not (run / "predictions" / f"{key}.npz").exists()
    ]
    if not todo:
        return []
    TrajectoryDataModule.from_run(run).sources()  # settings and data checked before any model
    written, data = [], {}
    for file in todo:
        surrogate = load_surrogate(file)
        target = run / "predictions" / f"{surrogate.name}.npz"
        if target.exists():
            continue
        kind = MeshGraphDataModule if surrogate.graph else TrajectoryDataModule
        if kind not in data:
            data[kind] = kind.from_run(run)
            data[kind].prepare_data()
            data[kind].setup()
        dm = data[kind]
        surrogate.check(dm.hparams.step, str(file))
        timed = not target.with_suffix(".json").exists()
        written.append(save_predictions(target, surrogate.predict, dm.val, timings=timed))
    return written


# --- files ---------------------------------------------------------------------------------


def predicted_trajectory(traj: Trajectory, shapes: BreastShapes, k: int) -> Trajectory:
    """``traj`` with the predicted steps of the ``k``-th thickness as its trajectories."""
    return replace(
        traj,
        unloaded=shapes.unloaded.astype(np.float64),
        compressed=shapes.compressed[k].astype(np.float64),
        plates=shapes.plates[k],
        compression_ratio=shapes.compression_ratio[k],
    )


def write_shapes(
    traj: Trajectory, shapes: BreastShapes, out_dir: str | Path, own_suffix: str | None = None
) -> list[Path]:
    """Write the predicted meshes into ``out_dir``, each atomically.

    ``unloaded.vtu`` (the unloaded shape), and per thickness t: ``compressed_<t>mm.vtu`` (the
    final shape) and ``trajectory_<t>mm.xdmf`` (the imaged mesh, every unloaded-state and
    compression step: a ParaView time series). With ``own_suffix`` (the input's format, e.g.
    ``.inp``) the final shapes are also written in that format when meshio can write it.
    """
    out = Path(out_dir)
    suffixes = [".vtu"] + (
        [own_suffix] if own_suffix and own_suffix not in (".vtu", ".npz") else []
    )
    written = []
    for suffix in suffixes:
        try:
            written.append(
                write_mesh(
                    replace(traj, points=shapes.unloaded[-1].astype(float)),
                    out / f"unloaded{suffix}",
                )
            )
            for k, t in enumerate(shapes.thickness):
                final = replace(traj, points=shapes.compressed[k, -1].astype(float))
                written.append(write_mesh(final, out / f"compressed_{t:g}mm{suffix}"))
        except (KeyError, ValueError, meshio.WriteError) as exc:  # meshio cannot write it
            print(f"not written in the input's format {suffix}: {exc}")
    for k, t in enumerate(shapes.thickness):
        written.append(
            write_time_series(
                predicted_trajectory(traj, shapes, k), out / f"trajectory_{t:g}mm.xdmf"
            )
        )
    return written


LATERALITIES = ("L", "R")


def thicknesses(setting: object) -> list[float]:
    """The ``thickness`` setting (a number or a list of numbers) as compressed thicknesses, mm.

    Raises
    ------
    ValueError
        Not a number nor a non-empty list of numbers, or a thickness that is not finite and
        positive; the message names the setting.
    """
    scalar = setting is None or isinstance(setting, str | int | float)
    values = [setting] if scalar else list(setting)
    try:
        out = [float(t) for t in values]
    except (TypeError, ValueError):
        out = []
    if not out or not all(math.isfinite(t) and t > 0 for t in out):
        raise ValueError(
            f"thickness must be a compressed thickness in mm (> 0) or a non-empty list of them, "
            f"got {setting!r}"
        )
    return out


def check_laterality(setting: str | None) -> None:
    """Refuse a ``laterality`` setting other than L, R or None (the file's)."""
    if setting not in (None, *LATERALITIES):
        raise ValueError(f"laterality must be L, R or null (the file's), got {setting!r}")


def set_laterality(traj: Trajectory, setting: str | None) -> None:
    """Record the ``laterality`` setting in ``traj``; without one, the file must record it.

    Raises
    ------
    ValueError
        No laterality in the setting nor in the file; the message names the file and the
        setting.
    """
    if setting is not None:
        traj.metadata["laterality"] = setting
    elif traj.metadata.get("laterality") not in LATERALITIES:
        raise ValueError(
            f"{traj.source}: metadata field 'laterality' must be 'L' or 'R', got "
            f"{traj.metadata.get('laterality')!r}: set laterality=L or laterality=R"
        )


def write_previews(
    traj: Trajectory, shapes: BreastShapes, models: tuple[str, str], title: str, out_dir: Path
) -> list[Path]:
    """``preview_<t>mm.png`` per thickness: the imaged, unloaded and compressed shapes in three
    body planes, with the names of the (unloaded-state, compression) ``models``."""
    written = []
    for k, t in enumerate(shapes.thickness):
        rows = {
            "imaged": traj.points,
            f"unloaded ({models[0]})": shapes.unloaded[-1],
            f"compressed to {t:g} mm ({models[1]})": shapes.compressed[k, -1],
        }
        written.append(
            shapes_sections_png(
                traj.cells,
                traj.tissue,
                rows,
                f"{title}: predicted shapes, {t:g} mm",
                Path(out_dir) / f"preview_{t:g}mm.png",
            )
        )
    return written


def read_landmarks(path: str | Path) -> tuple[list[str], NDArray[np.float64]]:
    """Names and coordinates (Q, 3) mm of the landmarks in a CSV with columns ``x, y, z``
    (and optionally ``name``).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        An empty file or not a text CSV, no landmark, a missing column, or a coordinate that
        is not a number.
    """
    path = Path(path)
    with reading_file(path, "a landmark CSV") as p, open(p, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path}: no landmarks (expected a header x,y,z and one row per point)")
    for field in ("x", "y", "z"):
        if field not in rows[0]:
            raise ValueError(f"{path}: field {field!r} missing (columns: {list(rows[0])})")
    names, points = [], []
    for i, row in enumerate(rows, start=1):
        names.append(row.get("name") or str(i))
        try:
            points.append([float(row[c]) for c in ("x", "y", "z")])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: row {i}: fields x, y, z must be numbers ({exc})") from exc
    return names, np.array(points)


def map_landmarks(
    traj: Trajectory,
    shapes: BreastShapes,
    names: Sequence[str],
    points: NDArray,
    source_to_image: float | None = SOURCE_TO_IMAGE_MM,
    source: str = "landmarks",
) -> list[dict[str, float | str]]:
    """Landmarks carried to the unloaded shape and to each compressed shape, and projected
    onto the detector of the cranio-caudal view (under the lower plate; the X-ray source above
    the middle of the breast's chest-wall edge). One row per landmark and thickness, mm."""
    cell, weights = locate(traj.points, traj.cells, points)
    outside = np.flatnonzero(cell < 0)
    if len(outside):
        i = outside[0]
        raise ValueError(
            f"{source}: landmark {names[i]!r} at {points[i].round(1).tolist()} mm lies outside "
            f"the breast mesh (bounds {traj.points.min(0).round(1).tolist()} to "
            f"{traj.points.max(0).round(1).tolist()} mm)"
        )
    unloaded = carry(shapes.unloaded[-1], traj.cells, cell, weights)  # (Q, 3)
    compressed = carry(shapes.compressed[:, -1], traj.cells, cell, weights)  # (K, Q, 3)
    rows = []
    for k, t in enumerate(shapes.thickness):
        final = shapes.compressed[k, -1]
        lower = shapes.plates[k, -1, 0, ORIGIN]  # the lower plate's chest-side edge (x, y, z)
        foot = (float(final[:, 0].mean()), float(lower[1]))
        detector = project_cc(compressed[k], float(lower[2]), foot, source_to_image)
        for q, name in enumerate(names):
            rows.append(
                {"name": name, "thickness_mm": float(t)}
                | dict(zip(("x", "y", "z"), points[q], strict=True))
                | dict(zip(("unloaded_x", "unloaded_y", "unloaded_z"), unloaded[q], strict=True))
                | dict(zip(("compressed_x", "compressed_y", "compressed_z"), compressed[k, q], strict=True))
                | dict(zip(("detector_x", "detector_y"), detector[q], strict=True))
            )  # fmt: skip
    return rows


def write_rows(rows: Sequence[dict], path: str | Path) -> Path:
    """Rows of `map_landmarks` as CSV (numbers in mm to 0.001), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(
            {k: f"{v:.3f}" if isinstance(v, float) else v for k, v in r.items()} for r in rows
        )
    return path
