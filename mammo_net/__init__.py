"""Lightning models, tree baselines and metrics (the learning pipeline, issue 4)."""
