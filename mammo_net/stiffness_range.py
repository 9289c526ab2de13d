"""Turn `mammo_net.module.MeshGraphModule.stiffness_range` on in graph models trained before
the setting existed: record the range of the moduli of each run's training breasts in its
checkpoint. The weights stay as trained; inside the range the setting changes no prediction,
outside it the network is shown the breast scaled uniformly into the range and the
compliance gain extrapolates (`mammo_net.models.scaled_into_range`).

    python -m mammo_net.stiffness_range 'results/cv_v2/mesh_gnn/unloaded/fold[0-9]'

Each run is a finished train.py run folder of a graph model with the compliance gain on. Its
training breasts are those of its own split, rebuilt from the plain values of its
``.hydra/config.yaml`` (`datamodules.graphs.MeshGraphDataModule.from_run`: nothing in it is
instantiated), so the trajectories it trained on must be in place. The checkpoint is
replaced atomically, and the run's saved predictions (``predictions/mesh_gnn.npz``, now
stale) are removed; their timing file is kept.
"""

from __future__ import annotations

import argparse
import glob
from pathlib import Path

import torch

from datamodules.graphs import MeshGraphDataModule, stiffness_bounds
from fem.contract.atomic import atomic_path
from mammo_net.module import MeshGraphModule, NetworkModule
from mammo_net.predictor import RUN_MODELS


def record_stiffness_range(run: str | Path) -> torch.Tensor:
    """Record the training breasts' range in the run's checkpoint and turn the setting on;
    returns the range (2, C) of `datamodules.graphs.stiffness_bounds`.

    Raises
    ------
    ValueError
        The run's checkpoint is not a graph model, has no compliance gain, or already
        records a range; the message names the file.
    """
    path = Path(run) / RUN_MODELS["network"]
    model = NetworkModule.from_checkpoint(path)
    if not isinstance(model, MeshGraphModule) or not model.scales_compliance:
        raise ValueError(f"{path}: not a graph model with the compliance gain (compliance_scaling)")
    if model.hparams.stiffness_range:
        raise ValueError(f"{path}: records its stiffness range already")
    dm = MeshGraphDataModule.from_run(run)
    dm.prepare_data()
    dm.setup()
    bounds = stiffness_bounds(dm.train)
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    checkpoint["hyper_parameters"]["stiffness_range"] = True
    checkpoint["state_dict"]["net.condition_bounds"] = bounds
    with atomic_path(path) as tmp:
        torch.save(checkpoint, tmp)
        MeshGraphModule.from_checkpoint(tmp)  # loads with the range, or nothing is replaced
    (Path(run) / "predictions" / f"{model.name}.npz").unlink(missing_ok=True)
    return bounds


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders (glob patterns allowed)")
    args = parser.parse_args(argv)
    runs = sorted({Path(p) for pattern in args.runs for p in glob.glob(pattern)})
    if not runs:
        parser.error(f"no run folder matches {' '.join(args.runs)}")
    for run in runs:
        bounds = record_stiffness_range(run)
        moduli = ", ".join(f"[{lo:.3f}, {hi:.3f}]" for lo, hi in bounds.T.tolist() if lo > -1e30)
        print(f"{run}: log-moduli against the reference {moduli}")


if __name__ == "__main__":
    main()
