"""FE simulation steps of the reference paper (section 2.1) on a `Trajectory` mesh.

The breast model is the tissue body (decoupled neo-Hookean tetrahedra with nodal volumetric
averaging) plus the skin, a 2 mm incompressible neo-Hookean membrane on the outer surface.

Step 1, the unloaded state: the breast was imaged prone, hanging anteriorly under gravity; a
body force ``rho g`` pointing posteriorly (-y in RAS+) removes that load, ramped in recorded
steps. The nodes of the muscle/breast interface are fixed in the anteroposterior direction
only and slide along the chest wall; the remaining rigid-body modes (translation in x and z,
rotation about y) are removed by pinning DOFs that carry no load for a load along y.

Step 2, compression: the unloaded shape is the stress-free reference; two rigid
plates perpendicular to z (`fem.contact`: exact non-penetration, Coulomb friction 0.25), the
lower at the inframammary fold, the upper moving down to the compressed thickness; the standing
patient's gravity along -z (switchable).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from fem.assembly import HyperelasticBody, Model
from fem.contact import RigidPlate
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

#: Coulomb friction coefficient between the skin and the compression plates (the paper's 0.25).
FRICTION = 0.25

#: Share of the volumetric energy kept on the elements with nodal averaging
#: (`fem.assembly.HyperelasticBody.stabilization`).
VOLUMETRIC_STABILIZATION = 0.1


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


def chest_wall_free_dofs(
    traj: Trajectory, source: str = "mesh", translations: tuple[int, ...] = (0, 2)
) -> NDArray[np.bool_]:
    """Free-DOF mask (N, 3): interface nodes fixed along y, plus load-free rigid-body pins.

    The pins: the interface node nearest the interface centroid is fixed along the axes in
    ``translations`` (x and z for the unloaded state; x only under the plates, which hold z);
    the interface node farthest from it in z is fixed in x, which stops the spin about y.
    Neither carries load when the loads act along y (step 1) or z (step 2).

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
    free[anchor, list(translations)] = False
    far = interface[np.argmax(np.abs(p[:, 2] - traj.points[anchor, 2]))]
    free[far, 0] = False
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
    stabilization = VOLUMETRIC_STABILIZATION if averaging == "nodal" else 0.0
    body = HyperelasticBody(traj.points, traj.cells, mu, kappa, averaging, stabilization)
    parts = ()
    if "skin" in materials and len(traj.skin):
        skin_mu, _ = lame_parameters(materials["skin"].young, materials["skin"].poisson)
        parts = (SkinMembrane(traj.points, traj.skin, float(skin_mu), SKIN_THICKNESS),)
    return Model(body, parts)


@dataclass
class CompressionResult:
    """Recorded compression steps: positions (T, N, 3), plate edges (T, 2, 2) as (y, z) of the
    lower and upper plate, and the compression ratio (T,)."""

    positions: NDArray
    plates: NDArray
    compression_ratio: NDArray


def compression(
    traj: Trajectory,
    start: NDArray,
    compressed_thickness: float,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    n_steps: int = 70,
    gravity: bool = True,
    averaging: str = "nodal",
    friction: float = FRICTION,
    settings: NewtonSettings = DEFAULT_NEWTON,
) -> CompressionResult:
    """Step 2: compress between two rigid plates perpendicular to z with Coulomb friction.

    The unloaded shape ``start`` (N, 3) is the stress-free reference. The lower plate sits at
    the lowest skin node (the inframammary fold); the upper plate starts at the highest skin
    node (first contact) and moves down to ``compressed_thickness`` above the lower one in
    ``n_steps`` recorded steps. Both plates reach back to the chest wall (their chest-side
    edge is at the most posterior muscle-interface node). The standing patient's gravity
    along -z (when ``gravity`` is true) is ramped with the plate travel. Both plates have the
    Coulomb coefficient ``friction`` (0: frictionless).
    """
    source = str(traj.metadata.get("source", "mesh"))
    moved = replace(traj, points=np.asarray(start, float))
    model = breast_model(moved, materials, averaging)
    skin_nodes = traj.flagged(NodeFlag.SKIN)
    bottom, top = float(start[skin_nodes, 2].min()), float(start[skin_nodes, 2].max())
    _check_thickness(compressed_thickness, top - bottom, source)
    free = chest_wall_free_dofs(moved, source, translations=(0,))
    interface = traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    edge = float(start[interface, AP_AXIS].min())
    n = len(start)
    # Both plates touch from the start (the lowest and the highest skin node): they hold the
    # breast vertically, so the chest-wall pins fix x only and carry no plate or gravity load.
    lower = RigidPlate(skin_nodes, bottom, +1, edge, n, friction)
    upper = RigidPlate(skin_nodes, top, -1, edge, n, friction)
    model = Model(model.body, (*model.parts, lower, upper))
    # The standing patient's gravity rises with the plate travel (it is fully on at the target).
    f = nodal_body_force(
        model.body, np.array([0.0, 0.0, -GRAVITY_FORCE_DENSITY if gravity else 0.0])
    )
    target = bottom + compressed_thickness
    record = np.arange(1, n_steps + 1) / n_steps

    def plate_height(s: NDArray | float) -> NDArray | float:
        return top - (top - target) * s

    heights = plate_height(record)

    def move(s: float) -> None:
        upper.height = plate_height(s)

    positions = load_ramp(
        model, start, free.ravel(), lambda s: s * f, record, settings, configure=move
    )
    plates = np.zeros((n_steps, 2, 2))
    plates[:, :, 0] = edge
    plates[:, 0, 1] = bottom
    plates[:, 1, 1] = heights
    return CompressionResult(positions, plates, 1.0 - (heights - bottom) / (top - bottom))


def _check_thickness(thickness: float, extent: float, source: str) -> None:
    if not 0 < thickness < extent:
        raise ValueError(
            f"{source}: compressed thickness {thickness:.1f} mm is not smaller than the breast's "
            f"cranio-caudal extent {extent:.1f} mm (or not positive)"
        )
