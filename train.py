"""Training entry point (Hydra): surrogates of the FE trajectories.

Delivered by issue 4 (the learning pipeline). Until then the main job is the cohort command,
``python -m fem.cohort``.
"""

import sys

if __name__ == "__main__":
    sys.exit(
        "train.py: the learning pipeline is not implemented yet (issue 4); run `python -m fem.cohort`"
    )
