"""Fit time of the tree baselines on a cohort's training split (the paper: XGBoost 4.5 h for 10 folds).

    python benchmarks/baseline_fit.py data/cohort/full/trajectories --step compression --model xgboost

Stacks the one-fold training split's (node, step) rows as the baseline callbacks do, then fits
the model with the hyperparameters of ``experiment=paper_<step>`` (composed from conf/)
``--repeats`` times and prints the rows, the median fit time and the process's peak memory.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

import mammo_net.module  # noqa: F401  (stores the model config node that conf/train.yaml composes)
from datamodules.trajectories import TrajectoryDataModule
from mammo_net import baselines

CONF = str(Path(__file__).resolve().parents[1] / "conf")
FIT = {"xgboost": baselines.fit_xgboost, "ert": baselines.fit_ert}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data_dir", help="folder of simulated trajectories (P0001_L.npz ...)")
    ap.add_argument("--step", choices=["unloaded", "compression"], default="compression")
    ap.add_argument("--model", choices=sorted(FIT), default="xgboost")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    dm = TrajectoryDataModule(args.data_dir, step=args.step)
    dm.prepare_data()
    dm.setup()
    X, Y = baselines.stack_rows(dm.rows(dm.train))
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment=paper_{args.step}"])
    params = {k: v for k, v in cfg.callbacks[args.model].items() if k != "_target_"}
    seconds = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        FIT[args.model](X, Y, **params)
        seconds.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
    print(
        f"{args.model} ({args.step}, {params}): {len(X)} rows x {X.shape[1]} features, "
        f"{len(dm.train)} training breasts; fit median {statistics.median(seconds):.0f} s "
        f"(runs {', '.join(f'{s:.0f}' for s in seconds)}); peak memory {peak:.1f} GiB"
    )


if __name__ == "__main__":
    main()
