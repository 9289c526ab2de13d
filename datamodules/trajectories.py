"""A LightningDataModule over folders of simulated trajectories (the FE cohort's output).

    dm = TrajectoryDataModule("data/cohort/full/trajectories", step="compression")
    dm = TrajectoryDataModule(["data/cohort/v2/trajectories", "data/cohort/v2/trajectories_mlo"])

`prepare_data` turns every ``P0007_L.npz`` into a per-breast feature cache
(``<cache_dir>/<step>/P0007_L.features.npy`` (N, T, F) float32, ``.targets.npy`` (N, T, 3)
float32 and ``.json`` with the normalisation, the simulation's conditions and the source file's
size and modification time), written atomically and skipped while the source is unchanged (a
re-simulated cohort is re-cached, never read from its old features).
Every dataset then reads the caches memory-mapped, so the cohort is never held in RAM twice:
the sequence model gets one node's step sequence per item, ``(T, F) -> (T, 3)``, and the tree
models get flat ``(node, step)`` rows (`TrajectoryDataModule.rows`) from the same split.
Splits are by patient (`datamodules.splits`): the paper's one-fold split or k-fold. Several
trajectory folders (the cohort v2's views: the same breasts in ``trajectories/`` and
``trajectories_mlo/``; or cohorts meshed at several resolutions) make one data set whose
breasts are named ``P0007_L@<label>``, the label being the folder's path below the folders'
common parent (`folder_labels`); a patient's breasts of every folder stay on one side of the
split. Augmentation folders (``augment_dir``: the same breasts remeshed at other resolutions and
simulated there) add training breasts only: their breasts of training patients join the
training set, those of validation patients are left out, and the split and the validation set
are those of ``data_dir`` alone.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import numpy as np
import torch
from numpy.typing import NDArray
from omegaconf import OmegaConf
from torch.utils.data import DataLoader, Dataset

from datamodules.features import (
    STEP_FEATURES,
    FeatureSchema,
    Normalization,
    compression_features,
    unloaded_features,
)
from datamodules.splits import TISSUES, check_bounds, k_folds, one_fold_split, within_bounds
from fem.contract.atomic import atomic_path
from fem.contract.trajectory import Trajectory

STEPS = {"unloaded": unloaded_features, "compression": compression_features}

#: The settings `TrajectoryDataModule.from_run` reads from a run folder, with their types
#: (a list: of str).
RUN_SETTINGS: dict[str, tuple[type, ...]] = {
    "data_dir": (str, list),
    "augment_dir": (str, list, type(None)),
    "augment_limit": (int, type(None)),
    "step": (str,),
    "split": (str, type(None)),
    "fold": (int, type(None)),
    "n_folds": (int,),
    "val_fraction": (float, int),
    "seed": (int,),
    "train_conditions": (dict, type(None)),
}


def limited_augmentation(
    breasts: list[Breast], labels: set[str], limit: int, seed: int
) -> list[Breast]:
    """``breasts`` with at most ``limit`` of each augmentation folder (its ``labels``), drawn
    with ``seed``; the data folders' breasts and the order are kept."""
    keep = {b.name for b in breasts if b.name.partition("@")[2] not in labels}
    rng = np.random.default_rng(seed)
    for label in sorted(labels):
        names = sorted(b.name for b in breasts if b.name.partition("@")[2] == label)
        keep.update(names if len(names) <= limit else rng.choice(names, limit, replace=False))
    return [b for b in breasts if b.name in keep]


#: A trajectory folder given as data: one path, or several.
DataDir = str | os.PathLike | Sequence[str | os.PathLike]


@dataclass(frozen=True)
class Breast:
    """One cached breast: its name, patient, site and cache file stem."""

    name: str
    patient: int
    site: str
    stem: Path

    def features(self) -> NDArray[np.float32]:
        """(N, T, F), memory-mapped."""
        return np.load(self.stem.with_suffix(".features.npy"), mmap_mode="r")

    def targets(self) -> NDArray[np.float32]:
        """(N, T, 3) normalised coordinates, memory-mapped."""
        return np.load(self.stem.with_suffix(".targets.npy"), mmap_mode="r")

    def normalization(self) -> Normalization:
        meta = json.loads(self.stem.with_suffix(".json").read_text())
        return Normalization.from_json(meta)

    def conditions(self) -> dict[str, float | str] | None:
        """The simulation's conditions (`recorded_conditions`), None if not recorded."""
        return json.loads(self.stem.with_suffix(".json").read_text())["conditions"]


@dataclass(frozen=True)
class Source:
    """One trajectory file of a data module: its breast's name and cache file stem."""

    name: str
    path: Path
    stem: Path


def data_folders(data_dir: DataDir, field: str = "data.data_dir") -> list[Path]:
    """The trajectory folders of ``data.data_dir`` (or of the config field ``field``): one
    folder, or a list of distinct folders (`folder_labels` tells their breasts apart).

    Raises
    ------
    ValueError
        No folder, a folder twice, or a folder inside another.
    """
    if isinstance(data_dir, str | os.PathLike):
        return [Path(data_dir)]
    folders = [Path(d) for d in data_dir]
    if not folders:
        raise ValueError(f"{field}: an empty list of trajectory folders")
    if len(folders) > 1:
        folder_labels(folders, field)
    return folders


def folder_labels(folders: Sequence[Path], field: str = "data.data_dir") -> list[str]:
    """What names the breasts and caches of each of several trajectory folders: its path below
    the folders' common parent, ``/`` written ``-`` (``trajectories`` and ``trajectories_mlo``
    for the views of one cohort v2, ``full-trajectories`` and ``2x-trajectories`` for
    ``data/cohort/full/trajectories`` and ``data/cohort/2x/trajectories``). ``field`` names
    the config field(s) the folders came from in the error.

    Raises
    ------
    ValueError
        A folder twice, or a folder inside another.
    """
    absolute = [Path(os.path.abspath(f)) for f in folders]
    common = Path(os.path.commonpath(absolute))
    labels = ["-".join(f.relative_to(common).parts) for f in absolute]
    twice = sorted(
        {str(f) for f, label in zip(folders, labels, strict=True) if labels.count(label) > 1}
    )
    if twice or "" in labels:
        raise ValueError(
            f"{field}: {twice or [str(common)]} given twice or holding another of "
            f"{[str(f) for f in folders]}: each folder names its breasts "
            "(<file stem>@<its path below the folders' common parent>)"
        )
    return labels


def recorded_conditions(metadata: Mapping) -> dict[str, float | str] | None:
    """The conditions a trajectory was simulated under (``metadata["simulation"]``) as plain
    values: ``young_<tissue>`` (Pa, `TISSUES`), ``friction``, ``view`` and ``angle`` (degrees);
    None when the metadata do not record them all."""
    sim = metadata.get("simulation")
    try:
        young = {f"young_{t}": float(sim["materials"][t]["young"]) for t in TISSUES}
        return {
            **young,
            "friction": float(sim["friction"]),
            "view": str(sim["view"]),
            "angle": float(sim["angle"]),
        }
    except (KeyError, TypeError, ValueError):
        return None


def source_stamp(source: Path) -> list[int]:
    """The trajectory file's size (bytes) and modification time (ns): a cache of another
    version of the file is stale."""
    stat = source.stat()
    return [stat.st_size, stat.st_mtime_ns]


def cache_is_current(source: Path, stem: Path, last: str = ".targets.npy") -> bool:
    """Whether ``stem``'s cache is complete (its file ``last`` is written last), of ``source``
    as it is, and records the conditions (caches written before they were are rebuilt)."""
    if not stem.with_suffix(last).exists():
        return False
    meta = json.loads(stem.with_suffix(".json").read_text())
    return meta.get("source_stamp") == source_stamp(source) and "conditions" in meta


def cache_meta(traj: Trajectory, source: Path, norm: Normalization, n_steps: int) -> dict:
    """The ``.json`` of a breast's cache: normalisation, patient, site, node and step counts,
    the simulation's conditions and the source's stamp."""
    return {
        **norm.to_json(),
        "patient": int(traj.metadata.get("patient", -1)),
        "site": str(traj.metadata.get("site", "")),
        "n_nodes": traj.n_nodes,
        "n_steps": n_steps,
        "conditions": recorded_conditions(traj.metadata),
        "source_stamp": source_stamp(source),
    }


def cache_breast(source: Path, stem: Path, step: str) -> None:
    """Write the feature cache of one simulated breast (atomically; targets last)."""
    traj = Trajectory.load(source)
    traj.metadata.setdefault("source", str(source))
    features, targets, norm = STEPS[step](traj)
    meta = cache_meta(traj, source, norm, len(targets))
    with atomic_path(stem.with_suffix(".features.npy")) as tmp:
        np.save(tmp, np.ascontiguousarray(features.transpose(1, 0, 2)))
    with atomic_path(stem.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(meta))
    with atomic_path(stem.with_suffix(".targets.npy")) as tmp:
        np.save(tmp, np.ascontiguousarray(targets.transpose(1, 0, 2)))


def node_offsets(breasts: list[Breast]) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Where each breast's nodes start in a dataset of all their nodes, (B + 1,) with the
    total last, and each breast's normalisation scale (mm per unit), (B,), from the caches."""
    metas = [json.loads(b.stem.with_suffix(".json").read_text()) for b in breasts]
    offsets = np.concatenate([[0], np.cumsum([m["n_nodes"] for m in metas])]).astype(np.int64)
    return offsets, np.array([m["scale"] for m in metas], np.float32)


class NodeSequences(Dataset):
    """One item per (breast, node): features (T, F) and targets (T, 3) float32, the breast's
    index in ``breasts``, its normalisation scale (mm per normalised unit, for errors in mm)
    and the item's index (so metrics can drop the repeats a distributed sampler pads with).
    """

    def __init__(self, breasts: list[Breast]) -> None:
        self.breasts = breasts
        self.offsets, self.scales = node_offsets(breasts)
        self._open: dict[int, tuple[NDArray, NDArray]] = {}

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def locate(self, index: int) -> tuple[int, int]:
        """(breast index, node index) of a dataset index."""
        b = int(np.searchsorted(self.offsets, index, side="right") - 1)
        return b, index - int(self.offsets[b])

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor, int, float, int]:
        b, node = self.locate(index)
        if b not in self._open:  # memory maps, opened lazily per worker
            self._open[b] = (self.breasts[b].features(), self.breasts[b].targets())
        features, targets = self._open[b]
        x = torch.from_numpy(np.array(features[node]))
        return x, torch.from_numpy(np.array(targets[node])), b, float(self.scales[b]), index


class TrajectoryDataModule(L.LightningDataModule):
    """Per-node step sequences and flat rows of one simulation step, split by patient.

    Parameters
    ----------
    data_dir : str or list of str
        Folder of simulated ``P*_[LR].npz`` trajectories, or several distinct folders (the
        views of the cohort v2, cohorts of several resolutions): their breasts are named
        ``<file stem>@<label>`` (`folder_labels`: ``P0007_L@trajectories_mlo``), one
        folder's by the file stem.
    step : {"unloaded", "compression"}
        Which simulation step the models learn.
    split : {"one_fold", "k_fold"}, optional
        The paper's 90/10 split with a site-balanced validation set, or k-fold
        cross-validation; by default k-fold when ``fold`` is given, else one-fold (so
        ``-m data.fold=0,1,...,9`` is the 10-fold cross-validation).
    fold : int, optional
        The validation fold of the k-fold split.
    n_folds, val_fraction, seed
        Split parameters (`datamodules.splits`).
    batch_size, num_workers
        Of the sequence loaders.
    cache_dir : str, optional
        Feature caches; default ``<data_dir>/cache`` (each folder's own); with several
        folders ``<cache_dir>/<label>``.
    train_conditions : mapping of str to [low, high], optional
        Bounds on the simulation conditions of the training breasts
        (`datamodules.splits.BOUNDED_CONDITIONS`: ``young_fat``, ``young_gland``,
        ``young_muscle``, ``young_skin`` in Pa, ``friction``, ``angle`` in degrees, mlo breasts
        only), bounds included: a training breast outside one is left out of training; the
        validation breasts are all kept, in and out of the bounds.
    augment_dir : str or list of str, optional
        Folders of more trajectories for training only (e.g. the cohort's breasts remeshed at
        2x and 4x the elements, `benchmarks/resolution_generalisation.py`): the breasts of
        training patients join the training set, named ``<file stem>@<label>`` (labels over
        ``data_dir`` and these folders together); those of validation patients are left out.
        The split is drawn over ``data_dir``'s patients alone.
    augment_limit : int, optional
        At most this many training breasts from each augmentation folder, drawn with ``seed``
        among its breasts of training patients: a fixed share of remeshed breasts however
        many a folder holds. Default: all of them.
    """

    #: A breast's cache is complete once its file of this suffix exists (written last).
    cache_last = ".targets.npy"
    #: The breasts read from the caches.
    breast_type: type[Breast] = Breast

    def __init__(
        self,
        data_dir: DataDir,
        step: str = "compression",
        split: str | None = None,
        fold: int | None = None,
        n_folds: int = 10,
        val_fraction: float = 0.1,
        seed: int = 0,
        batch_size: int = 256,
        num_workers: int = 0,
        cache_dir: str | None = None,
        train_conditions: Mapping[str, Sequence[float]] | None = None,
        augment_dir: DataDir | None = None,
        augment_limit: int | None = None,
    ) -> None:
        super().__init__()
        if step not in STEPS:
            raise ValueError(f"data.step must be one of {sorted(STEPS)}, got {step!r}")
        split = split or ("one_fold" if fold is None else "k_fold")
        if split not in ("one_fold", "k_fold"):
            raise ValueError(f"data.split must be 'one_fold' or 'k_fold', got {split!r}")
        if split == "k_fold" and n_folds < 2:
            raise ValueError(f"data.n_folds must be at least 2 for k_fold, got {n_folds!r}")
        if split == "k_fold" and not 0 <= (fold or 0) < n_folds:
            raise ValueError(
                f"data.fold must be in 0..{n_folds - 1} for k_fold (data.n_folds={n_folds}), "
                f"got {fold!r}"
            )
        if split == "one_fold" and fold is not None:
            raise ValueError(
                f"data.fold={fold} selects a k-fold validation fold; the one-fold split has none"
            )
        if augment_limit is not None and (
            not isinstance(augment_limit, int)
            or isinstance(augment_limit, bool)
            or augment_limit < 1
        ):
            raise ValueError(
                f"data.augment_limit must be a positive number of breasts or null, "
                f"got {augment_limit!r}"
            )
        folders = data_folders(data_dir)
        extra = [] if augment_dir is None else data_folders(augment_dir, "data.augment_dir")
        self.bounds = check_bounds(train_conditions)
        # the resolved values, stated, the folders as given (a relative folder stays relative
        # in checkpoints); a subclass's own arguments are not collected
        self.save_hyperparameters(
            {
                "data_dir": os.fspath(data_dir)
                if isinstance(data_dir, str | os.PathLike)
                else [os.fspath(d) for d in data_dir],
                "augment_dir": None if augment_dir is None else [os.fspath(d) for d in extra],
                "augment_limit": augment_limit,
                "step": step,
                "split": split,
                "fold": fold,
                "n_folds": n_folds,
                "val_fraction": val_fraction,
                "seed": seed,
                "batch_size": batch_size,
                "num_workers": num_workers,
                "cache_dir": cache_dir,
                "train_conditions": None
                if self.bounds is None
                else {name: list(pair) for name, pair in self.bounds.items()},
            }
        )
        #: the data folders, then the augmentation folders
        self.folders = [f.absolute() for f in folders + extra]
        self.n_data_dirs = len(folders)
        #: per folder, the suffix of its breasts' names (none for one data folder alone; an
        #: augmentation folder's always has one)
        self.labels = (
            folder_labels(folders + extra, "data.data_dir and data.augment_dir")
            if len(self.folders) > 1
            else [""]
        )
        if len(folders) == 1:
            self.labels[0] = ""
        if not cache_dir:
            self.caches = [f / "cache" for f in self.folders]
        else:
            self.caches = [Path(cache_dir).absolute() / label for label in self.labels]
        self.feature_names = STEP_FEATURES[step]
        self.train: list[Breast] = []
        self.val: list[Breast] = []

    @classmethod
    def from_run(cls, run: str | Path, data_dir: DataDir | None = None) -> TrajectoryDataModule:
        """The data module a ``train.py`` run folder was trained with, rebuilt from the plain
        values of its ``.hydra/config.yaml`` (`RUN_SETTINGS`; other keys, ``_target_``
        included, are ignored): a run folder may come from anyone, so nothing named in it is
        ever instantiated. ``data_dir`` replaces the run's own trajectory folder(s).

        Raises
        ------
        FileNotFoundError
            The folder has no ``.hydra/config.yaml``.
        ValueError
            The config is unreadable or a setting has the wrong type or value; the message
            names the file and the field.
        """
        config = Path(run) / ".hydra" / "config.yaml"
        if not config.is_file():
            raise FileNotFoundError(f"{config}: not found; is {run} a train.py run folder?")
        try:
            data = OmegaConf.load(config).data
            values = {
                k: OmegaConf.to_container(data[k], resolve=True)
                if OmegaConf.is_config(data[k])
                else data[k]
                for k in RUN_SETTINGS
                if k in data
            }
        except Exception as exc:  # YAML, a missing data section, unresolvable interpolations
            raise ValueError(f"{config}: unreadable data settings ({exc})") from exc
        for key, types in RUN_SETTINGS.items():
            value = values.get(key)
            if key in values and not (
                isinstance(value, types)
                and (not isinstance(value, list) or all(isinstance(v, str) for v in value))
            ):
                names = " or ".join("list of str" if t is list else t.__name__ for t in types)
                raise ValueError(f"{config}: field 'data.{key}' must be {names}, got {value!r}")
        if data_dir is not None:
            values["data_dir"] = data_dir
        try:
            return cls(**values)
        except ValueError as exc:  # a value the constructor refuses, e.g. data.fold
            raise ValueError(f"{config}: {exc}") from exc

    @property
    def data_dirs(self) -> list[Path]:
        """The data folders (absolute)."""
        return self.folders[: self.n_data_dirs]

    @property
    def augment_dirs(self) -> list[Path]:
        """The augmentation folders (absolute): training breasts only."""
        return self.folders[self.n_data_dirs :]

    @property
    def cache_kind(self) -> str:
        """The folder of this module's caches in each cache folder."""
        return self.hparams.step

    def write_cache(self, source: Path, stem: Path) -> None:
        """Cache one breast (`cache_breast`)."""
        cache_breast(source, stem, self.hparams.step)

    def sources(self) -> list[Source]:
        """Every trajectory file of the data folders, with its breast's name and cache stem.

        Raises
        ------
        FileNotFoundError
            A folder has no trajectory; the message names it.
        """
        result = []
        for folder, cache, label in zip(self.folders, self.caches, self.labels, strict=True):
            files = sorted(folder.glob("P*_[LR].npz"))
            if not files:
                raise FileNotFoundError(f"{folder}: no simulated trajectories (P*_[LR].npz)")
            result += [
                Source(
                    f"{f.stem}@{label}" if label else f.stem, f, cache / self.cache_kind / f.stem
                )
                for f in files
            ]
        return result

    def source(self, name: str) -> Path:
        """The trajectory file of breast ``name`` (named as by `sources`; nothing is read).

        Raises
        ------
        ValueError
            ``name`` names none of the folders (data and augmentation).
        """
        stem, _, label = name.partition("@")
        for d, own in zip(self.folders, self.labels, strict=True):
            if own == label:
                return d / f"{stem}.npz"
        raise ValueError(
            f"breast {name!r}: none of the data folders {[str(d) for d in self.folders]} "
            "(breasts of several folders are named <file stem>@<folder path below their "
            f"common parent>: {self.labels})"
        )

    def prepare_data(self) -> None:
        """Cache every breast not cached yet or changed since (`cache_is_current`); a cache
        folder is created by the first breast written, so a folder without (readable)
        trajectories gets none."""
        for s in self.sources():
            if not cache_is_current(s.path, s.stem, self.cache_last):
                self.write_cache(s.path, s.stem)

    def breasts(self) -> list[Breast]:
        result = []
        for s in self.sources():
            meta = json.loads(s.stem.with_suffix(".json").read_text())
            result.append(self.breast_type(s.name, meta["patient"], meta["site"], s.stem))
        return result

    def setup(self, stage: str | None = None) -> None:
        breasts = self.breasts()
        augment = set(self.labels[self.n_data_dirs :])
        own = [b for b in breasts if b.name.partition("@")[2] not in augment]
        site = {b.patient: b.site for b in own}
        patients = np.array(sorted(site))
        sites = [site[p] for p in patients]
        hp = self.hparams
        if hp.split == "one_fold":
            _, val = one_fold_split(patients, sites, hp.val_fraction, hp.seed)
        else:
            fold = k_folds(patients, sites, hp.n_folds, hp.seed)
            val = patients[fold == (hp.fold or 0)]
        held = set(val.tolist())
        self.val = [b for b in own if b.patient in held]
        self.train = [b for b in breasts if b.patient not in held]
        folders = ", ".join(map(str, self.data_dirs))
        if not self.train or not self.val:
            raise ValueError(
                f"{folders}: {len(patients)} patients give an empty "
                f"{'training' if not self.train else 'validation'} split ({hp.split})"
            )
        if self.bounds is not None:
            self.train = [b for b in self.train if within_bounds(self.conditions(b), self.bounds)]
            if not self.train:
                raise ValueError(
                    f"data.train_conditions={hp.train_conditions}: no training breast of "
                    f"{folders} lies within the bounds ({hp.split}, fold {hp.fold})"
                )
        if hp.augment_limit is not None:
            self.train = limited_augmentation(self.train, augment, hp.augment_limit, hp.seed)

    def conditions(self, breast: Breast) -> dict[str, float | str]:
        """A breast's recorded simulation conditions (`recorded_conditions`).

        Raises
        ------
        ValueError
            Its trajectory does not record them; the message names the file.
        """
        conditions = breast.conditions()
        if conditions is None:
            raise ValueError(
                f"{self.source(breast.name)}: metadata field 'simulation' must hold materials "
                f"(young of {', '.join(TISSUES)}), friction, view and angle for "
                "data.train_conditions"
            )
        return conditions

    def train_dataloader(self) -> DataLoader:
        return DataLoader(
            NodeSequences(self.train),
            batch_size=self.hparams.batch_size,
            shuffle=True,
            num_workers=self.hparams.num_workers,
        )

    def val_dataloader(self) -> DataLoader:
        return DataLoader(
            NodeSequences(self.val),
            batch_size=self.hparams.batch_size,
            num_workers=self.hparams.num_workers,
        )

    def test_dataloader(self) -> DataLoader:
        return self.val_dataloader()

    def max_steps(self) -> int:
        """The longest cached trajectory's step count."""
        return max(
            json.loads(s.stem.with_suffix(".json").read_text())["n_steps"] for s in self.sources()
        )

    def schema(self) -> FeatureSchema:
        """The feature schema of models trained here (the longest trajectory's step count)."""
        return FeatureSchema.of(self.hparams.step, self.max_steps())

    def feature_statistics(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and standard deviation (F,) of each feature over the training rows, streamed
        breast by breast (for the sequence model's standardisation)."""
        n, total, squares = 0, 0.0, 0.0
        for features, _ in self.rows(self.train):
            f = features.astype(np.float64)
            n, total, squares = n + len(f), total + f.sum(0), squares + (f**2).sum(0)
        mean = total / n
        return mean, np.sqrt(np.maximum(squares / n - mean**2, 0.0))

    @staticmethod
    def rows(breasts: list[Breast]) -> Iterator[tuple[NDArray, NDArray]]:
        """Flat ``(node, step)`` rows per breast for the tree models: ``(N * T, F)`` features
        and ``(N * T, 3)`` targets, one breast at a time (read from the memory maps)."""
        for b in breasts:
            f, t = b.features(), b.targets()
            yield np.asarray(f).reshape(-1, f.shape[-1]), np.asarray(t).reshape(-1, 3)
