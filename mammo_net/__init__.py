"""Lightning models, tree baselines and metrics."""
