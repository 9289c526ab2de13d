"""Shared fixtures: one small phantom breast and its mesh, built once per session."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from fem.breasts.mesh import Mesher
from fem.breasts.phantom import LabelVolume, PhantomGenerator
from fem.contract.plates import cc_plates
from fem.contract.trajectory import Tissue, Trajectory
from fem.engine.linear import condensed


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


def assert_exact_derivatives(
    part, x: np.ndarray, seed: int = 0, eps: float = 1e-6, rtol: float = 1e-6
) -> None:
    """A part's force is the gradient of its energy and its tangent the (symmetric) Jacobian
    of its force, checked by central differences along a random direction."""
    d = np.random.default_rng(seed).standard_normal(x.shape)
    dW = (part.energy(x + eps * d) - part.energy(x - eps * d)) / (2 * eps)
    assert part.internal_force(x) @ d.ravel() == pytest.approx(dW, rel=rtol)
    df = (part.internal_force(x + eps * d) - part.internal_force(x - eps * d)) / (2 * eps)
    K = condensed(part.tangent(x))
    np.testing.assert_allclose(K @ d.ravel(), df, atol=rtol * np.abs(df).max())
    assert abs(K - K.T).max() <= 1e-9 * abs(K).max()


def tiny_trajectory(laterality: str = "R", **metadata) -> Trajectory:
    """Two tetrahedra sharing a face: a fat one of volume 1/6 and a muscle one of 1/3 mm^3."""
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -2]], float)
    cells = np.array([[0, 1, 2, 3], [0, 2, 1, 4]])
    unloaded = np.stack([points + np.array([0, -0.5 * s, 0]) for s in (1, 2)])  # (2, 5, 3)
    rest = unloaded[-1]
    compressed = np.stack([rest * [1, 1, 1 - 0.1 * s] for s in (1, 2, 3)])  # (3, 5, 3)
    # Plates: lower at z = -2, upper from z = 1 (first contact) down by 0.3 / 0.6 / 0.9.
    upper = 1.0 - 0.3 * np.arange(1, 4)
    plates = cc_plates([-1.0, -2.0], np.stack([np.full(3, -1.0), upper], axis=1))  # (y, z)
    return Trajectory(
        points=points,
        cells=cells,
        tissue=np.array([1, 3], np.uint8),  # fat, muscle
        node_tissue_code=np.array([3, 3, 3, 2, 1], np.uint8),
        node_flags=np.array([1, 0, 0, 1 | 4, 0], np.uint8),  # node 3: skin, upper contact
        skin=np.array([[0, 1, 3]]),
        unloaded=unloaded,
        compressed=compressed,
        plates=plates,
        compression_ratio=1 - (upper + 2.0) / 3.0,
        metadata={"laterality": laterality, **metadata},
    )


#: The conditions the FE records in ``metadata["simulation"]`` (what graph models read).
SIMULATION_METADATA = {
    "materials": {
        "fat": {"young": 1100.0, "poisson": 0.495},
        "gland": {"young": 2500.0, "poisson": 0.495},
        "muscle": {"young": 6000.0, "poisson": 0.495},
        "skin": {"young": 1000.0, "poisson": 0.495, "membrane": 2.0},
    },
    "friction": 0.25,
    "view": "cc",
    "angle": 45.0,
}


@pytest.fixture
def trajectory_folder(tmp_path):
    """12 patients (3 of site A), both breasts each: tiny simulated trajectories."""
    for p in range(12):
        for lat in "LR":
            site = "A" if p % 4 == 0 else "B"
            tiny_trajectory(lat, patient=p, site=site, simulation=SIMULATION_METADATA).save(
                tmp_path / f"P{p:04d}_{lat}.npz"
            )
    return tmp_path


def benchmark_module(name: str) -> ModuleType:
    """The script ``benchmarks/<name>.py`` as a module (benchmarks/ is not a package)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
