"""The finite-element side: making breasts, simulating them, and the data contract.

- `fem.contract`: the `Trajectory` dataclass (the only contract between ``fem`` and
  ``datamodules``) and what every part shares with it: atomic writes, mesh quality,
  time series, landmarks. It imports nothing else of the project.
- `fem.engine`: the FE engine (neo-Hookean tetrahedra, skin membrane, rigid plates with
  friction, the Newton/load-stepping solver and the paper's two simulation steps).
  It imports only `fem.contract`.
- `fem.breasts`: making breasts (virtual phantoms, reading a user's segmentation or mesh,
  meshing, figures, the simulated cohort). It imports `fem.engine` and `fem.contract`.
- the commands `fem.cohort`, `fem.simulate`, `fem.mesh_breast` (``python -m ...``) on top.

docs/architecture.md maps the whole project.
"""

from pathlib import Path

#: The Hydra configs (``conf/``), absolute: the console entry points run from anywhere.
CONFIG_DIR = str(Path(__file__).resolve().parents[1] / "conf")
