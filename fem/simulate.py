"""FE simulation steps of the reference paper (section 2.1) on a `Trajectory` mesh.

The breast model is the tissue body (decoupled neo-Hookean tetrahedra with nodal volumetric
averaging) plus the skin, a 2 mm incompressible neo-Hookean membrane on the outer surface.

Step 1, the unloaded state: the breast was imaged prone, hanging anteriorly under gravity; a
body force ``rho g`` pointing posteriorly (-y in RAS+) removes that load, ramped in recorded
steps. The nodes of the muscle/breast interface are fixed in the anteroposterior direction
only and slide along the chest wall; the remaining rigid-body modes (translation in x and z,
rotation about y) are removed by pinning DOFs that carry no load for a load along y.

Step 2 (plate compression) is not implemented yet.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fem.assembly import HyperelasticBody, Model
from fem.material import lame_parameters
from fem.membrane import SkinMembrane
from fem.solver import (
    DEFAULT_NEWTON,
    GRAVITY_FORCE_DENSITY,
    NewtonSettings,
    load_ramp,
    nodal_body_force,
)
from fem.trajectory import NodeFlag, Tissue, Trajectory

AP_AXIS = 1  #: anteroposterior axis (y, RAS+)


@dataclass(frozen=True)
class Material:
    """Neo-Hookean parameters of one tissue: Young's modulus (Pa) and Poisson's ratio."""

    young: float
    poisson: float = 0.495


#: The reference paper's tissue parameters.
PAPER_MATERIALS: dict[str, Material] = {
    "fat": Material(1100.0),
    "gland": Material(2500.0),
    "muscle": Material(6000.0),
    "skin": Material(1000.0),
}

#: Thickness of the skin membrane, mm (the paper's 2 mm membrane elements).
SKIN_THICKNESS = 2.0


def element_moduli(
    tissue: NDArray, materials: Mapping[str, Material], source: str = "mesh"
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Shear and bulk moduli (Pa) of each element from its tissue label.

    Raises
    ------
    ValueError
        A tissue present in the mesh has no entry in ``materials``.
    """
    mu, kappa = np.zeros(len(tissue)), np.zeros(len(tissue))
    for t in np.unique(tissue):
        name = Tissue(int(t)).name.lower()
        if name not in materials:
            raise ValueError(
                f"{source}: tissue '{name}' ({int((tissue == t).sum())} elements) has no material "
                f"parameters (given: {sorted(materials)})"
            )
        m = materials[name]
        mu[tissue == t], kappa[tissue == t] = lame_parameters(m.young, m.poisson)
    return mu, kappa


def chest_wall_free_dofs(traj: Trajectory, source: str = "mesh") -> NDArray[np.bool_]:
    """Free-DOF mask (N, 3): interface nodes fixed along y, plus load-free rigid-body pins.

    The pins: the interface node nearest the interface centroid is fixed in x and z; the
    interface node farthest from it (in the x-z plane) is fixed in the direction normal to
    the line joining them, which stops the rotation about y.

    Raises
    ------
    ValueError
        The mesh has no muscle/breast interface nodes.
    """
    interface = traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    if interface.size < 2:
        raise ValueError(
            f"{source}: no muscle/breast interface nodes (field 'node_flags'): the chest-wall boundary "
            "condition needs muscle elements in contact with fat or gland"
        )
    free = np.ones((traj.n_nodes, 3), bool)
    free[interface, AP_AXIS] = False
    p = traj.points[interface]
    anchor = interface[np.argmin(np.linalg.norm(p - p.mean(0), axis=1))]
    free[anchor, [0, 2]] = False
    offset = (traj.points[interface] - traj.points[anchor])[:, [0, 2]]
    far = interface[np.argmax(np.linalg.norm(offset, axis=1))]
    d = traj.points[far] - traj.points[anchor]
    free[far, 2 if abs(d[0]) >= abs(d[2]) else 0] = False
    return free


def unloaded_state(
    traj: Trajectory,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    n_steps: int = 100,
    force_density: float = GRAVITY_FORCE_DENSITY,
    averaging: str = "nodal",
    settings: NewtonSettings = DEFAULT_NEWTON,
) -> NDArray[np.float64]:
    """Step 1: reverse the prone gravity, ramped, recording ``n_steps`` equal load steps.

    Returns
    -------
    (n_steps, N, 3) float64
        Node positions, mm, at load factors ``1/n_steps, 2/n_steps, ..., 1``.
    """
    model = breast_model(traj, materials, averaging)
    free = chest_wall_free_dofs(traj, str(traj.metadata.get("source", "mesh"))).ravel()
    direction = np.zeros(3)
    direction[AP_AXIS] = -1.0  # posterior: undo the anterior pull of prone gravity
    f = nodal_body_force(model.body, force_density * direction)
    record = np.arange(1, n_steps + 1) / n_steps
    return load_ramp(model, traj.points, free, lambda s: s * f, record, settings)


def breast_model(
    traj: Trajectory, materials: Mapping[str, Material], averaging: str = "nodal"
) -> Model:
    """The tissue body and, when ``materials`` has ``"skin"``, the skin membrane on ``traj.skin``."""
    source = str(traj.metadata.get("source", "mesh"))
    mu, kappa = element_moduli(traj.tissue, materials, source)
    body = HyperelasticBody(traj.points, traj.cells, mu, kappa, averaging=averaging)
    parts = ()
    if "skin" in materials and len(traj.skin):
        skin_mu, _ = lame_parameters(materials["skin"].young, materials["skin"].poisson)
        parts = (SkinMembrane(traj.points, traj.skin, float(skin_mu), SKIN_THICKNESS),)
    return Model(body, parts)
