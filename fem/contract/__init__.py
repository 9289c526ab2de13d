"""The shared contract: the `Trajectory` dataclass and the helpers every part uses with it
(atomic writes, mesh quality measures, XDMF time series, landmarks). Imports nothing else
of the project."""
