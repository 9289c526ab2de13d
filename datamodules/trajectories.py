"""A LightningDataModule over a folder of simulated trajectories (the FE cohort's output).

    dm = TrajectoryDataModule("data/cohort/full/trajectories", step="compression")

`prepare_data` turns every ``P0007_L.npz`` into a per-breast feature cache
(``<cache_dir>/<step>/P0007_L.features.npy`` (N, T, F) float32, ``.targets.npy`` (N, T, 3)
float32 and ``.json`` with the normalisation and the source file's size and modification time),
written atomically and skipped while the source is unchanged (a re-simulated cohort is
re-cached, never read from its old features).
Every dataset then reads the caches memory-mapped, so the cohort is never held in RAM twice:
the sequence model gets one node's step sequence per item, ``(T, F) -> (T, 3)``, and the tree
models get flat ``(node, step)`` rows (`TrajectoryDataModule.rows`) from the same split.
Splits are by patient (`datamodules.splits`): the paper's one-fold split or k-fold.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
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
from datamodules.splits import k_folds, one_fold_split
from fem.contract.atomic import atomic_path
from fem.contract.trajectory import Trajectory

STEPS = {"unloaded": unloaded_features, "compression": compression_features}

#: The settings `TrajectoryDataModule.from_run` reads from a run folder, with their types.
RUN_SETTINGS: dict[str, tuple[type, ...]] = {
    "data_dir": (str,),
    "step": (str,),
    "split": (str, type(None)),
    "fold": (int, type(None)),
    "n_folds": (int,),
    "val_fraction": (float, int),
    "seed": (int,),
}


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


def source_stamp(source: Path) -> list[int]:
    """The trajectory file's size (bytes) and modification time (ns): a cache of another
    version of the file is stale."""
    stat = source.stat()
    return [stat.st_size, stat.st_mtime_ns]


def cache_is_current(source: Path, stem: Path, last: str = ".targets.npy") -> bool:
    """Whether ``stem``'s cache is complete (its file ``last`` is written last) and of
    ``source`` as it is."""
    if not stem.with_suffix(last).exists():
        return False
    meta = json.loads(stem.with_suffix(".json").read_text())
    return meta.get("source_stamp") == source_stamp(source)


def cache_breast(source: Path, stem: Path, step: str) -> None:
    """Write the feature cache of one simulated breast (atomically; targets last)."""
    traj = Trajectory.load(source)
    traj.metadata.setdefault("source", str(source))
    features, targets, norm = STEPS[step](traj)
    meta = {
        **norm.to_json(),
        "patient": int(traj.metadata.get("patient", -1)),
        "site": str(traj.metadata.get("site", "")),
        "n_nodes": traj.n_nodes,
        "n_steps": len(targets),
        "source_stamp": source_stamp(source),
    }
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
    data_dir : str
        Folder of simulated ``P*_[LR].npz`` trajectories.
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
        Feature caches; default ``<data_dir>/cache``.
    """

    def __init__(
        self,
        data_dir: str,
        step: str = "compression",
        split: str | None = None,
        fold: int | None = None,
        n_folds: int = 10,
        val_fraction: float = 0.1,
        seed: int = 0,
        batch_size: int = 256,
        num_workers: int = 0,
        cache_dir: str | None = None,
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
        # the resolved values, stated: a subclass's own arguments are not collected
        self.save_hyperparameters(
            {
                "data_dir": data_dir,
                "step": step,
                "split": split,
                "fold": fold,
                "n_folds": n_folds,
                "val_fraction": val_fraction,
                "seed": seed,
                "batch_size": batch_size,
                "num_workers": num_workers,
                "cache_dir": cache_dir,
            }
        )
        self.data_dir = Path(data_dir)
        self.cache = Path(cache_dir) if cache_dir else self.data_dir / "cache"
        self.feature_names = STEP_FEATURES[step]
        self.train: list[Breast] = []
        self.val: list[Breast] = []

    @classmethod
    def from_run(cls, run: str | Path, data_dir: str | Path | None = None) -> TrajectoryDataModule:
        """The data module a ``train.py`` run folder was trained with, rebuilt from the plain
        values of its ``.hydra/config.yaml`` (`RUN_SETTINGS`; other keys, ``_target_``
        included, are ignored): a run folder may come from anyone, so nothing named in it is
        ever instantiated. ``data_dir`` replaces the run's own trajectory folder.

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
            values = {k: data[k] for k in RUN_SETTINGS if k in data}
        except Exception as exc:  # YAML, a missing data section, unresolvable interpolations
            raise ValueError(f"{config}: unreadable data settings ({exc})") from exc
        for key, types in RUN_SETTINGS.items():
            if key in values and not isinstance(values[key], types):
                raise ValueError(
                    f"{config}: field 'data.{key}' must be {' or '.join(t.__name__ for t in types)}, "
                    f"got {values[key]!r}"
                )
        if data_dir is not None:
            values["data_dir"] = str(data_dir)
        try:
            return cls(**values)
        except ValueError as exc:  # a value the constructor refuses, e.g. data.fold
            raise ValueError(f"{config}: {exc}") from exc

    def sources(self) -> list[Path]:
        files = sorted(self.data_dir.glob("P*_[LR].npz"))
        if not files:
            raise FileNotFoundError(f"{self.data_dir}: no simulated trajectories (P*_[LR].npz)")
        return files

    def prepare_data(self) -> None:
        """Cache the features of every breast not cached yet or changed since
        (`cache_is_current`); the cache folder is created by the first breast written, so a
        folder without (readable) trajectories gets none."""
        out = self.cache / self.hparams.step
        for source in self.sources():
            stem = out / source.stem
            if not cache_is_current(source, stem):
                cache_breast(source, stem, self.hparams.step)

    def breasts(self) -> list[Breast]:
        out = self.cache / self.hparams.step
        result = []
        for source in self.sources():
            meta = json.loads((out / source.stem).with_suffix(".json").read_text())
            result.append(Breast(source.stem, meta["patient"], meta["site"], out / source.stem))
        return result

    def setup(self, stage: str | None = None) -> None:
        breasts = self.breasts()
        site = {b.patient: b.site for b in breasts}
        patients = np.array(sorted(site))
        sites = [site[p] for p in patients]
        hp = self.hparams
        if hp.split == "one_fold":
            _, val = one_fold_split(patients, sites, hp.val_fraction, hp.seed)
        else:
            fold = k_folds(patients, sites, hp.n_folds, hp.seed)
            val = patients[fold == (hp.fold or 0)]
        self.val = [b for b in breasts if b.patient in set(val.tolist())]
        self.train = [b for b in breasts if b.patient not in set(val.tolist())]
        if not self.train or not self.val:
            raise ValueError(
                f"{self.data_dir}: {len(patients)} patients give an empty "
                f"{'training' if not self.train else 'validation'} split ({hp.split})"
            )

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

    def schema(self) -> FeatureSchema:
        """The feature schema of models trained here (the longest trajectory's step count)."""
        out = self.cache / self.hparams.step
        n_steps = max(
            json.loads((out / s.stem).with_suffix(".json").read_text())["n_steps"]
            for s in self.sources()
        )
        return FeatureSchema.of(self.hparams.step, n_steps)

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
