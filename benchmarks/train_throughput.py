"""Training throughput of the Att-BLSTM on a trajectory cohort: sequences per second, epoch time.

    python benchmarks/train_throughput.py data/cohort/full/trajectories --step compression
    python benchmarks/train_throughput.py data/cohort/full/trajectories --step unloaded --device cuda

Builds the DataModule's one-fold split (the feature caches are made on first use), then times
``--batches`` training batches (data loading, forward, RMSE loss, backward, Adam step) after
``--warmup`` untimed ones, ``--repeats`` times. Prints the median sequences per second and the
time per epoch it implies for the training split (validation passes not included).
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from datamodules.trajectories import TrajectoryDataModule
from mammo_net.module import SurrogateModule

CONF = str(Path(__file__).resolve().parents[1] / "conf")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data_dir", help="folder of simulated trajectories (P0001_L.npz ...)")
    ap.add_argument("--step", choices=["unloaded", "compression"], default="compression")
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--batches", type=int, default=40, help="timed batches per repeat")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--num-workers", type=int, default=0)
    args = ap.parse_args()

    dm = TrajectoryDataModule(
        args.data_dir, step=args.step, batch_size=args.batch_size, num_workers=args.num_workers
    )
    dm.prepare_data()
    dm.setup()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):  # the paper's model
        cfg = compose("train", overrides=[f"experiment=paper_{args.step}"])
    model: SurrogateModule = instantiate(cfg.model, hidden=args.hidden)
    model.set_feature_normalization(*dm.feature_statistics(), dm.schema())
    model.to(args.device).train()
    optimizer = model.configure_optimizers()
    loader = dm.train_dataloader()
    batches = itertools.cycle(loader)

    def run(n: int) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            x, y, *_ = next(batches)  # (B, T, F), (B, T, 3)
            x, y = x.to(args.device, non_blocking=True), y.to(args.device, non_blocking=True)
            loss = torch.sqrt(torch.nn.functional.mse_loss(model(x), y))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    run(args.warmup)
    rates = [args.batches * args.batch_size / run(args.batches) for _ in range(args.repeats)]
    rate = statistics.median(rates)
    n_train = len(loader.dataset)
    n_steps, n_features = loader.dataset[0][0].shape
    print(
        f"step {args.step}: {n_train} training sequences of {n_steps} steps x "
        f"{n_features} features, batch {args.batch_size}, hidden {args.hidden}, "
        f"{args.device}, {torch.get_num_threads()} threads"
    )
    print(
        f"median of {args.repeats} x {args.batches} batches: {rate:.0f} sequences/s "
        f"(runs {min(rates):.0f}-{max(rates):.0f}); {n_train / rate / 60:.1f} min per epoch"
    )


if __name__ == "__main__":
    main()
