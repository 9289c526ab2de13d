"""Shared fixtures: one small phantom breast and its mesh, built once per session."""

from __future__ import annotations

import numpy as np
import pytest

from fem.mesh import Mesher
from fem.phantom import LabelVolume, PhantomGenerator
from fem.trajectory import Tissue


@pytest.fixture(scope="session")
def generator() -> PhantomGenerator:
    return PhantomGenerator(seed=7)


@pytest.fixture(scope="session")
def phantom(generator):
    """(LabelVolume, metadata) of patient 1's left breast."""
    return generator.breast(1, "L")


@pytest.fixture(scope="session")
def breast_mesh(phantom):
    volume, meta = phantom
    return Mesher()(volume, meta)


@pytest.fixture
def ellipsoid_volume() -> LabelVolume:
    """A half-ellipsoid of fat with a gland core on a 6 mm muscle slab, 1 mm voxels."""
    x, y, z = np.meshgrid(np.arange(-45, 46), np.arange(-8, 50), np.arange(-40, 41), indexing="ij")
    labels = np.zeros(x.shape, np.uint8)
    inside = (x / 42.0) ** 2 + (y / 45.0) ** 2 + (z / 38.0) ** 2 <= 1
    labels[inside & (y >= 0)] = Tissue.FAT
    labels[
        inside & (y >= 0) & ((x / 15.0) ** 2 + ((y - 18) / 15.0) ** 2 + (z / 15.0) ** 2 <= 1)
    ] = Tissue.GLAND
    labels[((x / 42.0) ** 2 + (z / 38.0) ** 2 <= 1) & (y < 0) & (y >= -6)] = Tissue.MUSCLE
    affine = np.eye(4)
    affine[:3, 3] = [-45, -8, -40]
    return LabelVolume(labels, affine, "ellipsoid")
