"""The report's data: each breast's FE truth and each model's node errors, merged by
(split, step) from run folders (`collect`); the types the tables (`mammo_net.report`) and the
figures (`mammo_net.report_figures`) share.
"""

from __future__ import annotations

import glob
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datamodules.trajectories import DataDir, TrajectoryDataModule, recorded_conditions
from fem.contract.trajectory import TISSUE_BIT, NodeFlag, Tissue, Trajectory
from mammo_net import evaluation as ev
from mammo_net.inference import load_prediction_seconds, load_predictions
from mammo_net.metrics import node_rmse
from mammo_net.predictor import RUN_MODELS, predict_run
from mammo_net.validity import ValidityProjection

#: Pure-tissue node codes (interface nodes, whose code has several bits, are left out).
TISSUE_CODES = {t.name.lower(): TISSUE_BIT[t] for t in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)}


@dataclass
class BreastTruth:
    """What the report needs of one simulated breast for one step."""

    name: str
    positions: NDArray[np.float64]  # (N, T, 3) FE node positions per recorded step, mm
    tissue_code: NDArray[np.uint8]  # (N,) paper's Table 2 code
    surface: NDArray[np.bool_]  # (N,) skin nodes
    compression_ratio: NDArray[np.float64] | None  # (T,) compression step only
    volume_cm3: float
    motion: float  # RMS over nodes of the last step's displacement from the step's start, mm
    fe_seconds: float  # the FE solver's wall time for this step, s
    path: Path
    conditions: dict[str, float | str] | None  # the simulation's, if recorded


@dataclass
class ModelResult:
    """One model's predictions of one step in one split, as node errors per breast."""

    model: str
    errors: dict[str, NDArray[np.float32]] = field(default_factory=dict)  # name -> (N, T) mm
    seconds: dict[str, float] = field(default_factory=dict)  # name -> prediction time, s
    sources: dict[str, Path] = field(default_factory=dict)  # name -> predictions file


@dataclass
class Evaluation:
    """All models of one (split, step): the breasts' truth and each model's errors."""

    split: str
    step: str
    truth: dict[str, BreastTruth]
    models: dict[str, ModelResult]

    @property
    def label(self) -> str:
        return f"{self.split}, {self.step}"

    @property
    def slug(self) -> str:
        return f"{self.split}_{self.step}".replace(" ", "_").replace("-", "_")


def load_truth(path: Path, step: str, name: str) -> BreastTruth:
    """The FE positions of ``step`` and the node facts of the trajectory file ``path`` of breast
    ``name``."""
    traj = Trajectory.load(path)
    positions = traj.compressed if step == "compression" else traj.unloaded
    if not len(positions):
        raise ValueError(f"{path}: field {step!r} has no simulated steps")
    seconds = traj.metadata.get("simulation", {}).get("seconds", {}).get(step, float("nan"))
    start = traj.reference_shape if step == "compression" else traj.points  # the step's start
    return BreastTruth(
        name=name,
        positions=positions.transpose(1, 0, 2),
        tissue_code=traj.node_tissue_code,
        surface=(traj.node_flags & NodeFlag.SKIN) > 0,
        compression_ratio=traj.compression_ratio if step == "compression" else None,
        volume_cm3=float(traj.metadata.get("breast_volume_cm3", float("nan"))),
        motion=float(np.sqrt(((positions[-1] - start) ** 2).sum(-1).mean())),
        fe_seconds=float(seconds),
        path=path,
        conditions=recorded_conditions(traj.metadata),
    )


def run_settings(
    run: Path, data_dir: DataDir | None = None
) -> tuple[str, str, TrajectoryDataModule]:
    """(split label, step, data module) of a run folder, from the plain values of its
    ``.hydra/config.yaml`` (`TrajectoryDataModule.from_run`, its trajectory folders replaced
    by ``data_dir`` when given; nothing in it is instantiated)."""
    dm = TrajectoryDataModule.from_run(run, data_dir)
    hp = dm.hparams
    label = f"{hp.n_folds}-fold CV" if hp.split == "k_fold" else "one-fold"
    return label, str(hp.step), dm


def collect(
    runs: Iterable[str | Path],
    data_dir: DataDir | None = None,
    exclude: Iterable[str | Path] = (),
    projection: ValidityProjection | None = None,
) -> list[Evaluation]:
    """Merge the predictions of run folders by (split, step) and score them against the FE.

    Parameters
    ----------
    runs
        Run folders (glob patterns allowed) holding ``predictions/<model>.npz``.
    data_dir
        The trajectory folder, or folders (breasts named as `TrajectoryDataModule.sources`
        names them); by default each run's own ``data.data_dir``.
    exclude
        Run folders (glob patterns allowed) left out of ``runs``.
    projection
        Applied to every predicted trajectory before it is scored, as ``predict.py`` applies
        it (`ValidityProjection.project_step`); None scores the raw predictions.
    """
    patterns = [str(pattern) for pattern in runs]
    left_out = {Path(p).resolve() for pattern in exclude for p in glob.glob(str(pattern))}
    folders = [
        Path(p)
        for pattern in patterns
        for p in sorted(glob.glob(pattern))
        if Path(p).resolve() not in left_out
    ]
    if not folders:
        raise FileNotFoundError(
            f"runs: no run folder matches {patterns} (exclude: {[str(e) for e in exclude]})"
        )
    evaluations: dict[tuple[str, str], Evaluation] = {}
    for run in folders:
        split, step, dm = run_settings(run, data_dir)
        predict_run(run)  # a run kept as model files: its predictions first
        files = sorted((run / "predictions").glob("*.npz"))
        if not files:
            continue
        e = evaluations.setdefault((split, step), Evaluation(split, step, {}, {}))
        for file in files:
            result = e.models.setdefault(file.stem, ModelResult(file.stem))
            seconds = load_prediction_seconds(file)
            for name, prediction in load_predictions(file).items():
                if name in result.errors:
                    raise ValueError(
                        f"{file}: breast {name} was already predicted in {result.sources[name]}"
                    )
                try:
                    source = dm.source(name)
                except ValueError as exc:  # a name of other data folders
                    raise ValueError(f"{file}: {exc}") from exc
                if name not in e.truth:
                    e.truth[name] = load_truth(source, step, name)
                truth = e.truth[name].positions
                if prediction.shape != truth.shape:
                    raise ValueError(
                        f"{file}: field {name!r} has shape {prediction.shape}, the FE "
                        f"trajectory {truth.shape}"
                    )
                if projection is not None:  # (N, T, 3), as predict.py writes it
                    steps = prediction.transpose(1, 0, 2)
                    steps = projection.project_step(Trajectory.load(source), step, steps)
                    prediction = steps.transpose(1, 0, 2)
                result.errors[name] = node_rmse(prediction, truth).astype(np.float32)
                result.sources[name] = file
                if name in seconds:
                    result.seconds[name] = seconds[name]
    if not evaluations:
        raise FileNotFoundError(
            f"no predictions/*.npz, nor model files to predict them with "
            f"({', '.join(RUN_MODELS.values())}), in {[str(f) for f in folders]}"
        )
    return sorted(evaluations.values(), key=lambda e: (e.split, e.step))


def ratio_curve(
    result: ModelResult, truth: dict[str, BreastTruth], width: float
) -> tuple[NDArray, NDArray, NDArray]:
    """Mean breast RMSE per compression-ratio bin over every recorded step of every breast:
    bin centres, means, counts (the paper's Fig. 12, 13)."""
    ratio = np.concatenate([truth[n].compression_ratio for n in result.errors])
    rmse = np.concatenate([e.mean(0) for e in result.errors.values()])
    return ev.binned_means(ratio, rmse, width)


def ranked_breasts(e: Evaluation) -> list[str]:
    """Breasts predicted by every model, from the lowest to the highest mean over the models of
    their all-steps RMSE."""
    common = set.intersection(*(set(r.errors) for r in e.models.values()))
    score = {n: np.mean([r.errors[n].mean() for r in e.models.values()]) for n in common}
    return sorted(score, key=lambda n: (score[n], n))
