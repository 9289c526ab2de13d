"""Making breasts: virtual phantoms, reading a user's segmentation or mesh, tetrahedral
meshing, figures, and the simulated cohort. Imports `fem.engine` and `fem.contract`."""
