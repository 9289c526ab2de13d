"""FE simulation steps of the reference paper (section 2.1) on a `Trajectory` mesh.

`Simulation` runs both steps on one breast; the command ``python -m fem.simulate`` (`fem.simulate`)
runs it on a user's file.

The breast model is the tissue body (decoupled neo-Hookean tetrahedra with nodal volumetric
averaging) plus the skin, a 2 mm incompressible neo-Hookean membrane on the outer surface.

Step 1, the unloaded state: the breast was imaged prone, hanging anteriorly under gravity; a
body force ``rho g`` pointing posteriorly (-y in RAS+) removes that load, ramped in recorded
steps. The nodes of the muscle/breast interface are fixed in the anteroposterior direction
only and slide along the chest wall; the remaining rigid-body modes (translation in x and z,
rotation about y) are removed by pinning DOFs that carry no load for a load along y.

Step 2, compression: the unloaded shape is the stress-free reference; two rigid
plates perpendicular to z (`fem.engine.contact`: exact non-penetration, Coulomb friction 0.25), the
lower at the inframammary fold, the upper moving down to the compressed thickness; the standing
patient's gravity along -z (switchable).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from fem.contract.plates import upgrade_v1_plates
from fem.contract.quality import boundary_faces, posterior_cut, signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.contact import RigidPlate
from fem.engine.material import lame_parameters
from fem.engine.membrane import SkinMembrane
from fem.engine.solver import (
    DEFAULT_NEWTON,
    GRAVITY_FORCE_DENSITY,
    NewtonSettings,
    SolverError,
    load_ramp,
    nodal_body_force,
)

AP_AXIS = 1  #: anteroposterior axis (y, RAS+)
T = TypeVar("T")


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
#: (`fem.engine.assembly.HyperelasticBody.stabilization`).
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


def chest_wall_nodes(traj: Trajectory) -> NDArray[np.int64]:
    """The breast's nodes on the chest wall: the muscle/breast interface (``MUSCLE_INTERFACE``
    nodes), or for a breast without muscle elements or such nodes the nodes of its flat
    posterior cut face (`fem.contract.quality.posterior_cut`), where a segmentation cropped at
    the chest wall ends."""
    interface = traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    if interface.size or (traj.tissue == Tissue.MUSCLE).any():
        return interface
    faces, _ = boundary_faces(traj.points, traj.cells)
    return np.unique(faces[posterior_cut(traj.points, faces)])


def chest_wall_free_dofs(
    traj: Trajectory, source: str = "mesh", translations: tuple[int, ...] = (0, 2)
) -> NDArray[np.bool_]:
    """Free-DOF mask (N, 3): chest-wall nodes (`chest_wall_nodes`) fixed along y, plus
    load-free rigid-body pins.

    The pins: the chest-wall node nearest their centroid is fixed along the axes in
    ``translations`` (x and z for the unloaded state; x only under the plates, which hold z);
    the chest-wall node farthest from it in z is fixed in x, which stops the spin about y.
    Neither carries load when the loads act along y (step 1) or z (step 2).

    Raises
    ------
    ValueError
        The mesh has no chest-wall nodes.
    """
    interface = chest_wall_nodes(traj)
    if interface.size < 2:
        raise ValueError(
            f"{source}: no muscle/breast interface nodes (field 'node_flags') and no flat "
            "posterior cut face: no chest wall to hold; give its nodes as simulation.fixed_nodes"
        )
    free = np.ones((traj.n_nodes, 3), bool)
    free[interface, AP_AXIS] = False
    p = traj.points[interface]
    anchor = interface[np.argmin(np.linalg.norm(p - p.mean(0), axis=1))]
    free[anchor, list(translations)] = False
    far = interface[np.argmax(np.abs(p[:, 2] - traj.points[anchor, 2]))]
    free[far, 0] = False
    return free


def boundary_free_dofs(
    traj: Trajectory,
    source: str,
    fixed: NDArray | None = None,
    translations: tuple[int, ...] = (0, 2),
) -> NDArray[np.bool_]:
    """Free-DOF mask (N, 3): the chest-wall condition, or the clamped nodes ``fixed``.

    Raises
    ------
    ValueError
        A ``fixed`` index outside the mesh, or no chest-wall nodes without ``fixed``.
    """
    if fixed is None:
        return chest_wall_free_dofs(traj, source, translations)
    fixed = np.asarray(fixed, np.int64)
    if fixed.size == 0 or fixed.min() < 0 or fixed.max() >= traj.n_nodes:
        raise ValueError(
            f"{source}: fixed nodes must be indices in [0, {traj.n_nodes}), got {fixed.size} "
            f"indices in [{fixed.min(initial=0)}, {fixed.max(initial=0)}]"
        )
    free = np.ones((traj.n_nodes, 3), bool)
    free[fixed] = False
    return free


def unloaded_state(
    traj: Trajectory,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    n_steps: int = 100,
    force_density: float = GRAVITY_FORCE_DENSITY,
    averaging: str = "nodal",
    settings: NewtonSettings = DEFAULT_NEWTON,
    fixed: NDArray | None = None,
) -> NDArray[np.float64]:
    """Step 1: reverse the prone gravity, ramped, recording ``n_steps`` equal load steps.

    ``fixed`` (node indices) clamps those nodes instead of the chest-wall condition
    (`chest_wall_free_dofs`), for meshes without a chest wall of their own.

    Returns
    -------
    (n_steps, N, 3) float64
        Node positions, mm, at load factors ``1/n_steps, 2/n_steps, ..., 1``.
    """
    model = breast_model(traj, materials, averaging)
    source = traj.source
    free = boundary_free_dofs(traj, source, fixed, translations=(0, 2)).ravel()
    direction = np.zeros(3)
    direction[AP_AXIS] = -1.0  # posterior: undo the anterior pull of prone gravity
    f = nodal_body_force(model.body, force_density * direction)
    record = np.arange(1, n_steps + 1) / n_steps
    return load_ramp(model, traj.points, free, lambda s: s * f, record, settings)


def breast_model(
    traj: Trajectory, materials: Mapping[str, Material], averaging: str = "nodal"
) -> Model:
    """The tissue body and, when ``materials`` has ``"skin"``, the skin membrane on ``traj.skin``."""
    source = traj.source
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


@dataclass(frozen=True)
class PlateSchedule:
    """Where the rigid plates of the compression step are.

    The lower plate sits at ``bottom``, the lowest skin node of the unloaded shape (the
    inframammary fold); the upper plate starts at ``top``, the highest skin node (first
    contact), and moves down to ``bottom + thickness`` at load factor 1. Both plates reach
    back to ``edge``, the y of their chest-side edge. Millimetres.
    """

    bottom: float
    top: float
    thickness: float
    edge: float

    def height(self, s: NDArray | float) -> NDArray | float:
        """Upper plate z at load factor ``s`` in [0, 1]."""
        return self.top - (self.top - self.bottom - self.thickness) * s

    def recorded(self, n_steps: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Plate frames (T, 2, 3, 3) of the lower and upper plate (`fem.contract.plates`) and
        the compression ratio (T,) at the ``n_steps`` equally spaced recorded load factors
        ``k / n_steps``."""
        heights = self.height(np.arange(1, n_steps + 1) / n_steps)
        plates = np.zeros((n_steps, 2, 2))
        plates[:, :, 0] = self.edge
        plates[:, 0, 1] = self.bottom
        plates[:, 1, 1] = heights
        # schema version 2: plate frames; the engine rewrite (any plate pose) replaces this
        return upgrade_v1_plates(plates), 1.0 - (heights - self.bottom) / (self.top - self.bottom)


def plate_schedule(
    traj: Trajectory, start: NDArray, compressed_thickness: float, fixed: NDArray | None = None
) -> PlateSchedule:
    """The plates that compress the unloaded shape ``start`` (N, 3) of ``traj``'s mesh to
    ``compressed_thickness`` (mm). Their chest-side edge is at the most posterior
    chest-wall node, or, with clamped nodes ``fixed``, at the most anterior of those.

    Raises
    ------
    ValueError
        The thickness is not positive or not below the breast's cranio-caudal extent.
    """
    skin_z = start[traj.flagged(NodeFlag.SKIN), 2]
    bottom, top = float(skin_z.min()), float(skin_z.max())
    _check_thickness(compressed_thickness, top - bottom, traj.source)
    if fixed is None:  # the plates reach back to the (sliding) chest wall
        edge = float(start[chest_wall_nodes(traj), AP_AXIS].min())
    else:  # ... or stop in front of the clamped nodes, which they could only crush
        edge = float(start[np.asarray(fixed), AP_AXIS].max())
    return PlateSchedule(bottom, top, float(compressed_thickness), edge)


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
    fixed: NDArray | None = None,
) -> CompressionResult:
    """Step 2: compress between two rigid plates perpendicular to z with Coulomb friction.

    The unloaded shape ``start`` (N, 3) is the stress-free reference. The lower plate sits at
    the lowest skin node (the inframammary fold); the upper plate starts at the highest skin
    node (first contact) and moves down to ``compressed_thickness`` above the lower one in
    ``n_steps`` recorded steps. Both plates reach back to the chest wall (their chest-side
    edge is at the most posterior chest-wall node). The standing patient's gravity
    along -z (when ``gravity`` is true) is ramped with the plate travel. Both plates have the
    Coulomb coefficient ``friction`` (0: frictionless). ``fixed`` as in `unloaded_state`
    (the plate edges are then at the most anterior clamped node).
    """
    source = traj.source
    schedule = plate_schedule(traj, start, compressed_thickness, fixed)
    moved = replace(traj, points=np.asarray(start, float))
    model = breast_model(moved, materials, averaging)
    skin_nodes = traj.flagged(NodeFlag.SKIN)
    free = boundary_free_dofs(moved, source, fixed, translations=(0,))
    n, edge = len(start), schedule.edge
    # Both plates touch from the start (the lowest and the highest skin node): they hold the
    # breast vertically, so the chest-wall pins fix x only and carry no plate or gravity load.
    lower = RigidPlate(skin_nodes, schedule.bottom, +1, edge, n, friction)
    upper = RigidPlate(skin_nodes, schedule.top, -1, edge, n, friction)
    model = Model(model.body, (*model.parts, lower, upper))
    # The standing patient's gravity rises with the plate travel (it is fully on at the target).
    f = nodal_body_force(
        model.body, np.array([0.0, 0.0, -GRAVITY_FORCE_DENSITY if gravity else 0.0])
    )
    record = np.arange(1, n_steps + 1) / n_steps

    def move(s: float) -> None:
        upper.height = schedule.height(s)

    positions = load_ramp(
        model, start, free.ravel(), lambda s: s * f, record, settings, configure=move
    )
    return CompressionResult(positions, *schedule.recorded(n_steps))


def _check_thickness(thickness: float, extent: float, source: str) -> None:
    if not 0 < thickness < extent:
        raise ValueError(
            f"{source}: compressed thickness {thickness:.1f} mm is not smaller than the breast's "
            f"cranio-caudal extent {extent:.1f} mm (or not positive)"
        )


def _timed(step: str, seconds: dict[str, float], source: str, run: Callable[[], T]) -> T:
    """Run one simulation step, record its wall time under its first word, and turn a
    `SolverError` into `SimulationFailed` (with the times so far)."""
    t0 = time.perf_counter()
    try:
        return run()
    except SolverError as exc:
        raise SimulationFailed(source, step, str(exc), seconds) from exc
    finally:
        seconds[step.split()[0]] = time.perf_counter() - t0


class SimulationFailed(RuntimeError):
    """A breast could not be simulated; ``step`` says which step, ``seconds`` what it cost."""

    def __init__(self, source: str, step: str, reason: str, seconds: dict[str, float]) -> None:
        super().__init__(f"{source}: {step} failed: {reason}")
        self.step, self.reason, self.seconds = step, reason, seconds


@dataclass
class Simulation:
    """Both steps of the reference paper on one breast, with one set of parameters.

    This is the ``simulation`` config group (`conf/simulation/default.yaml`); its keys are
    these arguments.

    Parameters
    ----------
    materials : mapping
        Tissue name (``fat``, ``gland``, ``muscle``, ``skin``) -> `Material` or a mapping with
        ``young`` (Pa) and optionally ``poisson``. Leaving out ``skin`` drops the membrane.
    unloaded_steps : int
        Recorded steps of the unloaded state (step 1).
    compression_steps : int
        Recorded steps of the compression (step 2).
    compression_ratio : float, optional
        Final compression ratio ``1 - thickness / extent``, with the cranio-caudal extent of
        the skin in the unloaded state (the plates' first contact). Default: the breast's
        ``metadata["target_compression_ratio"]`` (the virtual cohort's sampled ratio).
    friction : float
        Coulomb coefficient between skin and plates (0: frictionless).
    gravity : bool
        The standing patient's gravity during compression.
    averaging : {"nodal", "element"}
        Volumetric averaging (`fem.engine.assembly.HyperelasticBody`); ``element`` locks.
    prone_gravity : float
        Body force removed in step 1, Pa/mm (rho g; 0 skips the unloaded state's load).
    fixed_nodes : str, optional
        A text or ``.npy`` file of node indices to clamp instead of the chest-wall condition
        (sliding muscle/breast interface), for a model without muscle elements.
    """

    materials: Mapping[str, Material | Mapping[str, float]] = field(
        default_factory=lambda: dict(PAPER_MATERIALS)
    )
    unloaded_steps: int = 100
    compression_steps: int = 70
    compression_ratio: float | None = None
    friction: float = FRICTION
    gravity: bool = True
    averaging: str = "nodal"
    prone_gravity: float = GRAVITY_FORCE_DENSITY
    fixed_nodes: str | None = None

    def __post_init__(self) -> None:
        self.materials = {
            name: m if isinstance(m, Material) else Material(**m)
            for name, m in self.materials.items()
        }
        for name, m in self.materials.items():
            if not (m.young > 0 and 0 <= m.poisson < 0.5):
                raise ValueError(
                    f"simulation.materials.{name}: young must be > 0 Pa and poisson in "
                    f"[0, 0.5), got young={m.young}, poisson={m.poisson}"
                )
        rules = {  # setting: (holds, what it must)
            "compression_ratio": (
                self.compression_ratio is None or 0 < self.compression_ratio < 1,
                "lie in (0, 1)",
            ),
            "unloaded_steps": (self.unloaded_steps >= 1, "be at least 1"),
            "compression_steps": (self.compression_steps >= 1, "be at least 1"),
            "friction": (self.friction >= 0, "be >= 0 (0: frictionless)"),
            "averaging": (self.averaging in ("nodal", "element"), "be 'nodal' or 'element'"),
            "prone_gravity": (self.prone_gravity >= 0, "be >= 0 Pa/mm"),
        }
        for key, (holds, rule) in rules.items():
            if not holds:
                raise ValueError(f"simulation.{key} must {rule}, got {getattr(self, key)!r}")

    def target_ratio(self, traj: Trajectory) -> float:
        """The compression ratio to reach: the configured one or the breast's metadata."""
        if self.compression_ratio is not None:
            return float(self.compression_ratio)
        if "target_compression_ratio" not in traj.metadata:
            raise ValueError(
                f"{traj.source}: no compression ratio: set "
                "simulation.compression_ratio or metadata field 'target_compression_ratio'"
            )
        return float(traj.metadata["target_compression_ratio"])

    def __call__(self, traj: Trajectory) -> Trajectory:
        """Simulate both steps; returns a copy of ``traj`` with its trajectories filled in.

        Raises
        ------
        SimulationFailed
            A step did not converge (the reason names the load factor and Newton's trouble).
        ValueError
            Bad input (missing material, no chest wall, no compression ratio).
        """
        source = traj.source
        ratio = self.target_ratio(traj)
        fixed = None
        if self.fixed_nodes is not None:
            path = Path(self.fixed_nodes)
            try:
                fixed = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, dtype=np.int64)
            except (OSError, ValueError) as exc:
                raise ValueError(f"{path}: cannot read fixed node indices: {exc}") from exc
            fixed = np.atleast_1d(fixed).astype(np.int64)
        seconds: dict[str, float] = {}
        unloaded = _timed(
            "unloaded state",
            seconds,
            source,
            lambda: unloaded_state(
                traj,
                self.materials,
                self.unloaded_steps,
                self.prone_gravity,
                self.averaging,
                fixed=fixed,
            ),
        )
        skin_z = unloaded[-1][traj.flagged(NodeFlag.SKIN), 2]
        thickness = (1.0 - ratio) * float(np.ptp(skin_z))
        result = _timed(
            "compression",
            seconds,
            source,
            lambda: compression(
                traj,
                unloaded[-1],
                thickness,
                self.materials,
                self.compression_steps,
                self.gravity,
                self.averaging,
                self.friction,
                fixed=fixed,
            ),
        )
        reference = signed_volume(unloaded[-1], traj.cells).sum()
        final = result.positions[-1]
        metadata = {
            **traj.metadata,
            "simulation": {
                "materials": {k: vars(m) for k, m in self.materials.items()},
                "friction": self.friction,
                "gravity": self.gravity,
                "averaging": self.averaging,
                "prone_gravity": self.prone_gravity,
                "fixed_nodes": self.fixed_nodes,
                "compression_ratio": float(result.compression_ratio[-1]),
                "compressed_thickness_mm": thickness,
                "volume_change": float(signed_volume(final, traj.cells).sum() / reference - 1),
                "min_element_volume_ratio": float(
                    (
                        signed_volume(final, traj.cells) / signed_volume(traj.points, traj.cells)
                    ).min()
                ),
                "max_unloaded_displacement_mm": float(
                    np.linalg.norm(unloaded[-1] - traj.points, axis=1).max()
                ),
                "seconds": seconds,
            },
        }
        return replace(
            traj,
            unloaded=unloaded,
            compressed=result.positions,
            plates=result.plates,
            compression_ratio=result.compression_ratio,
            metadata=metadata,
        )
