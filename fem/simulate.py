"""Simulate one breast: both FE steps of the reference paper on a user's file.

    python -m fem.simulate input=data/cohort/default/P0000_L.npz [simulation.friction=0 ...]
    python -m fem.simulate input=case01.nii.gz reader.label_map.gland=[2,4]

reads the input (a Trajectory, a tetrahedral mesh or a segmentation, meshed first) with the
``reader`` group (`fem.breasts.io.BreastReader`) and writes the breast with both steps
(``<output>.npz``, a `Trajectory`) and an XDMF time series for ParaView (``<output>.xdmf``);
`conf/simulate.yaml` lists the options.
"""

from __future__ import annotations

import json
from pathlib import Path

import hydra
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig

from fem import CONFIG_DIR
from fem.contract.atomic import writable_folder
from fem.contract.timeseries import write_time_series


def simulate_file(cfg: DictConfig) -> Path:
    """Run the command on a composed config; returns the output stem."""
    source = Path(to_absolute_path(cfg.input))
    stem = (
        Path(to_absolute_path(cfg.output))
        if cfg.output
        else source.with_name(source.name.split(".")[0] + "_simulated")
    )
    simulation = instantiate(cfg.simulation)  # settings checked before any work
    writable_folder(stem.parent)
    traj = instantiate(cfg.reader)(source)
    simulated = simulation(traj)
    if cfg.time_series:
        write_time_series(simulated, stem.with_suffix(".xdmf"))
    simulated.save(stem.with_suffix(".npz"))
    print(json.dumps(simulated.metadata["simulation"], indent=2))
    print(f"wrote {stem}.npz" + (f", {stem}.xdmf" if cfg.time_series else ""))
    return stem


@hydra.main(config_path=CONFIG_DIR, config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    simulate_file(cfg)


if __name__ == "__main__":
    main()
