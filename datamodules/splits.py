"""Patient-level splits: the paper's one-fold split and k-fold cross-validation, and the
training set's bounds on the simulation conditions.

Both breasts of a patient (in every view) always stay on one side. Patients are identified by
an integer and carry a site label; splits are deterministic functions of the patient list and
a seed. Bounds on the conditions (``data.train_conditions``) hold training breasts out of
ranges of stiffness, friction or mlo angle (`check_bounds`, `within_bounds`); they never move
a patient between the sides.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray


def one_fold_split(
    patients: Sequence[int], sites: Sequence[str], val_fraction: float = 0.1, seed: int = 0
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Train and validation patients, the validation set balanced between the sites.

    The paper's one-fold validation (section 3): 90 % / 10 % of the breasts, the validation
    breasts half from each clinical site. ``round(val_fraction * n_patients)`` validation
    patients are drawn, split as evenly as the sites allow (a site keeps at least one training
    patient; the other sites make up what it cannot give).

    Returns
    -------
    train, val : int64 arrays
        Sorted patient ids.
    """
    patients, sites = np.asarray(patients), np.asarray(sites)
    _check(patients, sites)
    rng = np.random.default_rng(seed)
    names = sorted(set(sites.tolist()))
    n_val = max(1, round(val_fraction * len(patients)))
    pools = {s: rng.permutation(patients[sites == s]) for s in names}
    # Even shares per site, capped so that every site keeps a training patient.
    quota = {s: 0 for s in names}
    while sum(quota.values()) < n_val:
        open_sites = [s for s in names if quota[s] < len(pools[s]) - 1]
        if not open_sites:
            break
        quota[min(open_sites, key=lambda s: quota[s])] += 1
    val = np.sort(np.concatenate([pools[s][: quota[s]] for s in names]))
    return np.setdiff1d(patients, val), val


def k_folds(
    patients: Sequence[int], sites: Sequence[str], n_folds: int = 10, seed: int = 0
) -> NDArray[np.int64]:
    """Fold index of each patient for k-fold cross-validation, stratified by site.

    Returns
    -------
    (P,) int64
        Fold in ``0..n_folds-1`` of each entry of ``patients``; folds differ in size by at
        most one patient per site.
    """
    patients, sites = np.asarray(patients), np.asarray(sites)
    _check(patients, sites)
    if not 2 <= n_folds <= len(patients):
        raise ValueError(f"n_folds must lie in [2, {len(patients)}], got {n_folds}")
    rng = np.random.default_rng(seed)
    fold = np.empty(len(patients), np.int64)
    offset = 0
    for s in sorted(set(sites.tolist())):
        members = rng.permutation(np.flatnonzero(sites == s))
        fold[members] = (offset + np.arange(len(members))) % n_folds
        offset += len(members)  # continue the round robin across sites: balanced fold sizes
    return fold


def _check(patients: NDArray, sites: NDArray) -> None:
    if len(patients) != len(sites):
        raise ValueError(f"{len(patients)} patients but {len(sites)} site labels")
    if len(np.unique(patients)) != len(patients):
        raise ValueError("patient ids must be unique (one entry per patient, not per breast)")


#: The tissues whose Young's modulus a simulation records (``metadata["simulation"]``) and a
#: surrogate is conditioned on.
TISSUES = ("fat", "gland", "muscle", "skin")

#: The conditions ``data.train_conditions`` may bound (the names of
#: `datamodules.trajectories.recorded_conditions`): Young's moduli in Pa, the friction
#: coefficient, the mlo plates' angle in degrees (a cc breast satisfies any angle bounds).
BOUNDED_CONDITIONS = (*(f"young_{t}" for t in TISSUES), "friction", "angle")


def check_bounds(
    bounds: Mapping[str, Sequence[float]] | None,
) -> dict[str, tuple[float, float]] | None:
    """``data.train_conditions`` checked: condition name -> (low, high), or None for no bounds.

    Raises
    ------
    ValueError
        An unknown condition name, or bounds that are not two finite numbers with
        ``low <= high``; the message names ``data.train_conditions.<name>``.
    """
    if bounds is None:
        return None
    if not isinstance(bounds, Mapping):
        raise ValueError(
            f"data.train_conditions must map condition names to [low, high], got {bounds!r}"
        )
    checked = {}
    for name, pair in bounds.items():
        field = f"data.train_conditions.{name}"
        if name not in BOUNDED_CONDITIONS:
            raise ValueError(f"{field}: unknown condition; one of {', '.join(BOUNDED_CONDITIONS)}")
        numbers = list(pair) if isinstance(pair, Sequence) and not isinstance(pair, str) else [pair]
        if not (
            len(numbers) == 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in numbers)
            and all(math.isfinite(v) for v in numbers)
            and numbers[0] <= numbers[1]
        ):
            raise ValueError(f"{field} must be [low, high], finite with low <= high, got {pair!r}")
        checked[str(name)] = (float(numbers[0]), float(numbers[1]))
    return checked


def within_bounds(
    conditions: Mapping[str, float | str], bounds: Mapping[str, tuple[float, float]]
) -> bool:
    """Whether a breast's conditions (`datamodules.trajectories.recorded_conditions`) lie
    inside every bound (`check_bounds`), bounds included; the angle binds mlo breasts only."""
    return all(
        low <= conditions[name] <= high
        for name, (low, high) in bounds.items()
        if name != "angle" or conditions["view"] == "mlo"
    )
