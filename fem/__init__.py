"""Finite-element side: virtual patients, meshing, mesh I/O and (next) the FE solver."""
