"""LightningDataModules over FE trajectories."""
