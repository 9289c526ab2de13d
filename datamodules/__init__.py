"""LightningDataModules over FE trajectories (issue 4)."""
