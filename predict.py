"""Prediction entry point (Hydra): deformed meshes for a new breast.

Delivered by issue 6. Until then, ``fem.io.load_breast`` meshes a user's breast.
"""

import sys

if __name__ == "__main__":
    sys.exit("predict.py: prediction is not implemented yet (issue 6)")
