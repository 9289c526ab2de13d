"""FE simulation steps of the reference paper (section 2.1) on a `Trajectory` mesh.

`Simulation` runs both steps on one breast; the command ``python -m fem.simulate`` (`fem.simulate`)
runs it on a user's file.

The breast model is the tissue body (decoupled neo-Hookean tetrahedra with nodal volumetric
averaging, one material per tissue or per element set) plus the skin, a 2 mm incompressible
neo-Hookean membrane on the outer surface (or a solid element set).

Step 1, the unloaded state (optional): the breast was imaged prone, hanging anteriorly under
gravity; a body force ``rho g`` pointing posteriorly (-y in RAS+) removes that load, ramped in
recorded steps.

Step 2, compression: the unloaded shape is the stress-free reference; two parallel rigid
plates (`fem.engine.contact`: exact non-penetration, Coulomb friction 0.25), cranio-caudal or
mediolateral-oblique (`fem.engine.boundary.plate_schedule`), the lower at the breast's lowest
skin node along its normal, the upper moving down to the compressed thickness, or plates with
a prescribed pose and motion; the standing patient's gravity along -z.

In both steps the chest wall holds the breast (`fem.engine.boundary.chest_wall`: by default the
muscle does not deform and the interface slides along it), plus a user's held directions.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.boundary import (
    CHEST_WALLS,
    FASCIA_STIFFNESS,
    VIEWS,
    ChestWallFascia,
    PlateSchedule,
    chest_wall,
    chest_wall_fascia,
    plate_schedule,
    read_constraints,
)
from fem.engine.constraints import HeldDirections, NodeFrames, equilibrium_path
from fem.engine.contact import RigidPlate
from fem.engine.linear import BACKENDS
from fem.engine.material import lame_parameters
from fem.engine.membrane import SkinMembrane
from fem.engine.solver import (
    DEFAULT_NEWTON,
    GRAVITY_FORCE_DENSITY,
    NewtonSettings,
    SolverError,
    nodal_body_force,
)

T = TypeVar("T")

#: Thickness of the skin membrane, mm (the paper's 2 mm membrane elements).
SKIN_THICKNESS = 2.0


@dataclass(frozen=True)
class Material:
    """Neo-Hookean parameters of one tissue or element set.

    Either Young's modulus (Pa) and Poisson's ratio, or the shear and bulk moduli ``mu`` and
    ``kappa`` (Pa). ``elements`` (a text or ``.npy`` file of element indices) makes it an
    element set, applied after the tissues; without it the name must be a tissue (``fat``,
    ``gland``, ``muscle``) or ``skin``, the membrane of thickness ``membrane`` (mm; default
    `SKIN_THICKNESS`). A skin with ``elements`` is a solid set and there is no membrane.
    """

    young: float | None = None
    poisson: float = 0.495
    mu: float | None = None
    kappa: float | None = None
    elements: str | None = None
    membrane: float | None = None

    def check(self, name: str) -> None:
        """Raise ``ValueError`` naming ``simulation.materials.<name>`` for bad parameters."""
        key = f"simulation.materials.{name}"
        if (self.young is None) == (self.mu is None) or (self.mu is None) != (self.kappa is None):
            raise ValueError(f"{key}: give young (and poisson) or mu and kappa, not both/neither")
        if self.young is not None and not (self.young > 0 and 0 <= self.poisson < 0.5):
            raise ValueError(
                f"{key}: young must be > 0 Pa and poisson in [0, 0.5), got young={self.young}, "
                f"poisson={self.poisson}"
            )
        if self.mu is not None and not (self.mu > 0 and self.kappa > 0):
            raise ValueError(f"{key}: mu and kappa must be > 0 Pa, got {self.mu}, {self.kappa}")
        if self.membrane is not None and (
            name != "skin" or self.elements is not None or not self.membrane > 0
        ):
            raise ValueError(f"{key}: membrane (thickness > 0 mm) is for a skin without elements")
        if self.elements is None and name not in TISSUE_NAMES and name != "skin":
            raise ValueError(
                f"{key}: '{name}' is not a tissue ({', '.join(TISSUE_NAMES)}, skin): give its "
                "elements file"
            )

    def moduli(self) -> tuple[float, float]:
        """Shear and bulk moduli, Pa."""
        if self.mu is not None:
            return float(self.mu), float(self.kappa)
        return lame_parameters(self.young, self.poisson)

    @property
    def is_membrane(self) -> bool:
        return self.elements is None and self.membrane is not None


TISSUE_NAMES = tuple(t.name.lower() for t in Tissue if t != Tissue.BACKGROUND)

#: The reference paper's tissue parameters.
PAPER_MATERIALS: dict[str, Material] = {
    "fat": Material(1100.0),
    "gland": Material(2500.0),
    "muscle": Material(6000.0),
    "skin": Material(1000.0, membrane=SKIN_THICKNESS),
}

#: Coulomb friction coefficient between the skin and the compression plates (the paper's 0.25).
FRICTION = 0.25

#: Share of the volumetric energy kept on the elements with nodal averaging
#: (`fem.engine.assembly.HyperelasticBody.stabilization`).
VOLUMETRIC_STABILIZATION = 0.1

#: Body forces of the steps, Pa/mm: prone gravity removed (posterior), standing gravity.
UNLOADED_GRAVITY = (0.0, -GRAVITY_FORCE_DENSITY, 0.0)
STANDING_GRAVITY = (0.0, 0.0, -GRAVITY_FORCE_DENSITY)


def read_indices(path: str | Path, what: str) -> NDArray[np.int64]:
    """Integer indices from a text or ``.npy`` file; ``what`` names the setting in errors."""
    path = Path(path)
    try:
        values = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read indices ({what}): {exc}") from exc
    values = np.atleast_1d(values).ravel()
    if values.size == 0 or not np.all(values == np.round(values)):
        raise ValueError(f"{path}: {what} must be a non-empty list of integer indices")
    return values.astype(np.int64)


def element_moduli(
    tissue: NDArray,
    materials: Mapping[str, Material],
    source: str = "mesh",
    sets: Mapping[str, NDArray] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Shear and bulk moduli (Pa) of each element: by tissue label, then element sets.

    ``sets`` maps a material name to its element indices (the materials with ``elements``).

    Raises
    ------
    ValueError
        An element has no material (a tissue without parameters and no set covering it).
    """
    mu, kappa = np.full(len(tissue), np.nan), np.full(len(tissue), np.nan)
    for t in np.unique(tissue):
        name = Tissue(int(t)).name.lower()
        if name in materials and materials[name].elements is None:
            mu[tissue == t], kappa[tissue == t] = materials[name].moduli()
    for name, elements in (sets or {}).items():
        if elements.min() < 0 or elements.max() >= len(tissue):
            raise ValueError(
                f"{materials[name].elements}: element indices of simulation.materials.{name} "
                f"must lie in [0, {len(tissue)}), got [{elements.min()}, {elements.max()}]"
            )
        mu[elements], kappa[elements] = materials[name].moduli()
    missing = np.isnan(mu)
    if missing.any():
        names = sorted({Tissue(int(t)).name.lower() for t in tissue[missing]})
        raise ValueError(
            f"{source}: tissue {', '.join(map(repr, names))} ({int(missing.sum())} elements) has "
            f"no material parameters (given: {sorted(materials)})"
        )
    return mu, kappa


def breast_model(
    traj: Trajectory,
    materials: Mapping[str, Material],
    averaging: str = "nodal",
    sets: Mapping[str, NDArray] | None = None,
    fascia: ChestWallFascia | None = None,
) -> Model:
    """The tissue body, when ``materials`` has a membrane ``"skin"`` the skin membrane on
    ``traj.skin``, and the chest wall's ``fascia`` if any."""
    mu, kappa = element_moduli(traj.tissue, materials, traj.source, sets)
    stabilization = VOLUMETRIC_STABILIZATION if averaging == "nodal" else 0.0
    body = HyperelasticBody(traj.points, traj.cells, mu, kappa, averaging, stabilization)
    parts = ()
    skin = materials.get("skin")
    if skin is not None and skin.is_membrane and len(traj.skin):
        parts = (SkinMembrane(traj.points, traj.skin, skin.moduli()[0], skin.membrane),)
    return Model(body, parts if fascia is None else (*parts, fascia))


def unloaded_state(
    traj: Trajectory,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    n_steps: int = 100,
    body_force: Sequence[float] = UNLOADED_GRAVITY,
    averaging: str = "nodal",
    settings: NewtonSettings = DEFAULT_NEWTON,
    chest: str = "sliding",
    fascia: float = FASCIA_STIFFNESS,
    held: HeldDirections | None = None,
    sets: Mapping[str, NDArray] | None = None,
) -> NDArray[np.float64]:
    """Step 1: reverse the prone gravity, ramped, recording ``n_steps`` equal load steps.

    Parameters
    ----------
    body_force : (3,) float
        Body force applied, Pa/mm (default: the prone gravity removed, ``rho g`` along -y).
    chest : str
        The chest-wall condition (`fem.engine.boundary.chest_wall`).
    fascia : float
        The sliding chest wall's tangential stiffness per unit area, Pa/mm
        (`fem.engine.boundary.ChestWallFascia`).
    held : HeldDirections, optional
        A user's held directions, added to the chest wall's.

    Returns
    -------
    (n_steps, N, 3) float64
        Node positions, mm, at load factors ``1/n_steps, 2/n_steps, ..., 1``.
    """
    support = chest_wall_fascia(traj, traj.points, chest, fascia)
    model = breast_model(traj, materials, averaging, sets, support)
    held_all = chest_wall(traj, traj.points, chest, (0, 2)) + (held or HeldDirections.none())
    frames = NodeFrames.build(traj.n_nodes, held_all)
    f = nodal_body_force(model.body, np.asarray(body_force, float))
    record = np.arange(1, n_steps + 1) / n_steps
    return equilibrium_path(model, frames, traj.points, lambda s: s * f, record, settings)


@dataclass
class CompressionResult:
    """Recorded compression steps: positions (T, N, 3), plates (T, 2, 3, 3) as rows origin,
    normal, axis of the lower and upper plate, and the compression ratio (T,)."""

    positions: NDArray
    plates: NDArray
    compression_ratio: NDArray


def compression(
    traj: Trajectory,
    start: NDArray,
    schedule: PlateSchedule,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    n_steps: int = 70,
    body_force: Sequence[float] = STANDING_GRAVITY,
    averaging: str = "nodal",
    friction: float = FRICTION,
    settings: NewtonSettings = DEFAULT_NEWTON,
    chest: str = "sliding",
    fascia: float = FASCIA_STIFFNESS,
    held: HeldDirections | None = None,
    sets: Mapping[str, NDArray] | None = None,
) -> CompressionResult:
    """Step 2: compress between two parallel rigid plates with Coulomb friction.

    The shape ``start`` (N, 3) is the stress-free reference. The plates follow ``schedule``
    (`fem.engine.boundary.plate_schedule`: from first contact to the compressed thickness) in
    ``n_steps`` recorded steps; both touch the skin nodes (candidates) in front of their
    chest-side edge, with the Coulomb coefficient ``friction`` (0: frictionless). The body
    force (the standing patient's gravity, Pa/mm) is ramped with the plate travel.
    """
    moved = replace(traj, points=np.asarray(start, float))
    model = breast_model(
        moved, materials, averaging, sets, chest_wall_fascia(moved, start, chest, fascia)
    )
    skin_nodes = traj.flagged(NodeFlag.SKIN)
    n = len(start)
    lower_frame, upper_frame = schedule.frames(0.0)
    plates = [
        RigidPlate(skin_nodes, *frame, n, friction, extent=schedule.extent)
        for frame in (lower_frame, upper_frame)
    ]
    for plate in plates:  # which nodes it bounds; no contact force yet
        plate.start(moved.points)
        plate.accept(moved.points, np.zeros(len(skin_nodes)))
    model = Model(model.body, (*model.parts, *plates))
    held_all = chest_wall(moved, moved.points, chest, (0,)) + (held or HeldDirections.none())
    behind = skin_nodes[~plates[0].front]
    frames = NodeFrames.build(n, held_all, lower_frame[1], skin_nodes, lower_frame[2], behind)
    f = nodal_body_force(model.body, np.asarray(body_force, float))
    record = np.arange(1, n_steps + 1) / n_steps

    def move(s: float) -> None:
        for plate, frame in zip(plates, schedule.frames(s), strict=True):
            plate.origin = frame[0]

    positions = equilibrium_path(
        model, frames, moved.points, lambda s: s * f, record, settings, configure=move
    )
    return CompressionResult(positions, *schedule.recorded(n_steps))


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


def shape_changes(points: NDArray, cells: NDArray, start: NDArray, final: NDArray) -> dict:
    """The checks recorded with a simulation: the volume change from ``start`` (the unloaded
    shape) to ``final``, the smallest element volume ratio of ``final`` to the imaged
    ``points`` and the largest unloaded-state displacement, mm; all (N, 3) positions."""
    final_volumes = signed_volume(final, cells)
    return {
        "volume_change": float(final_volumes.sum() / signed_volume(start, cells).sum() - 1),
        "min_element_volume_ratio": float((final_volumes / signed_volume(points, cells)).min()),
        "max_unloaded_displacement_mm": float(np.linalg.norm(start - points, axis=1).max()),
    }


class SimulationFailed(RuntimeError):
    """A breast could not be simulated; ``step`` says which step, ``seconds`` what it cost."""

    def __init__(self, source: str, step: str, reason: str, seconds: dict[str, float]) -> None:
        super().__init__(f"{source}: {step} failed: {reason}")
        self.step, self.reason, self.seconds = step, reason, seconds
        self.source = source

    def __reduce__(self) -> tuple:  # picklable: it crosses process pools
        return type(self), (self.source, self.step, self.reason, self.seconds)


def plate_schedule_from(settings: Mapping[str, Any]) -> PlateSchedule:
    """A `PlateSchedule` from the ``simulation.plates`` setting: ``lower`` and ``upper``, each
    with ``origin``, ``normal`` (into the breast), ``axis`` (away from the chest) and
    ``travel`` (mm at the end of the step, default none), and optionally ``extent``
    (length, width; mm).

    Raises
    ------
    ValueError
        A missing or malformed entry, vectors that are not orthogonal unit vectors, or plates
        that are not parallel; the message names the setting.
    """
    frames, travels = [], []
    for name in ("lower", "upper"):
        plate = settings.get(name) if isinstance(settings, Mapping) else None
        if not isinstance(plate, Mapping):
            raise ValueError(f"simulation.plates.{name} is missing (origin, normal, axis, travel)")
        rows = []
        for key in ("origin", "normal", "axis", "travel"):
            value = np.asarray(plate.get(key, (0.0, 0.0, 0.0) if key == "travel" else None))
            if value.shape != (3,) or not np.isfinite(value.astype(float)).all():
                raise ValueError(
                    f"simulation.plates.{name}.{key} must be 3 numbers (mm), got {value}"
                )
            rows.append(value.astype(float))
        origin, normal, axis, travel = rows
        if (
            abs(np.linalg.norm(normal) - 1) > 1e-6
            or abs(np.linalg.norm(axis) - 1) > 1e-6
            or abs(normal @ axis) > 1e-6
        ):
            raise ValueError(
                f"simulation.plates.{name}: normal {normal} and axis {axis} must be orthogonal "
                "unit vectors"
            )
        frames.append(np.stack([origin, normal, axis]))
        travels.append(travel)
    if np.abs(frames[0][1] + frames[1][1]).max() > 1e-6:
        raise ValueError(
            "simulation.plates: the plates must be parallel, facing each other (upper normal = "
            f"-lower normal), got {frames[0][1]} and {frames[1][1]}"
        )
    extent = tuple(float(e) for e in settings.get("extent", (np.inf, np.inf)))
    return PlateSchedule(frames[0], frames[1], travels[0], travels[1], extent)


@dataclass
class Simulation:
    """Both steps of the reference paper on one breast, or a user's own problem.

    This is the ``simulation`` config group (`conf/simulation/default.yaml`); its keys are
    these arguments. docs/fem.md shows a published model written as such a config.

    Parameters
    ----------
    materials : mapping
        Name -> `Material` or a mapping of its arguments: tissues (``fat``, ``gland``,
        ``muscle``), element sets (any name, with ``elements``) and ``skin`` (the membrane,
        or a solid set with ``elements``; leaving it out drops the membrane).
    unloaded_steps : int
        Recorded steps of the unloaded state (step 1); 0 skips it (the compression starts from
        the imaged shape).
    compression_steps : int
        Recorded steps of the compression (step 2).
    compression_ratio : float, optional
        Final compression ratio ``1 - thickness / extent``, with the skin's extent along the
        plate normal in the unloaded state (the plates' first contact). Default: the breast's
        ``metadata["target_compression_ratio"]``. Not used with ``plates``.
    friction : float
        Coulomb coefficient between skin and plates (0: frictionless).
    view : {"cc", "mlo"}
        Cranio-caudal or mediolateral-oblique plates (`fem.engine.boundary.plate_schedule`).
    angle : float
        The mlo plates' angle from the cc plates about the anteroposterior axis, degrees.
    plates : mapping, optional
        Plates with a given pose and motion instead of the view (`plate_schedule_from`).
    unloaded_gravity, compression_gravity : (3,) float
        Body force of each step, Pa/mm: by default the prone gravity removed (``rho g`` along
        -y) and the standing patient's (along -z); zeros switch it off.
    averaging : {"nodal", "element"}
        Volumetric averaging (`fem.engine.assembly.HyperelasticBody`); ``element`` locks.
    chest_wall : {"sliding", "tied", "anteroposterior", "none"}
        How the chest wall holds the breast (`fem.engine.boundary.chest_wall`).
    fascia_stiffness : float
        The sliding chest wall's tangential stiffness per unit area of wall, Pa/mm
        (`fem.engine.boundary.ChestWallFascia`; 0: free sliding).
    constraints : str, optional
        A file of held nodes and directions (`fem.engine.boundary.read_constraints`), added to
        the chest wall's.
    linear_solver : {"auto", "superlu", "pardiso"}
        Newton's sparse factorization (`fem.engine.linear`): ``auto`` takes MKL PARDISO from
        1,000 DOFs on (the cohort's meshes too) when the optional ``mkl`` wheel is installed,
        SuperLU otherwise.
    """

    materials: Mapping[str, Material | Mapping[str, Any]] = field(
        default_factory=lambda: dict(PAPER_MATERIALS)
    )
    unloaded_steps: int = 100
    compression_steps: int = 70
    compression_ratio: float | None = None
    friction: float = FRICTION
    view: str = "cc"
    angle: float = 45.0
    plates: Mapping[str, Any] | None = None
    unloaded_gravity: Sequence[float] = UNLOADED_GRAVITY
    compression_gravity: Sequence[float] = STANDING_GRAVITY
    averaging: str = "nodal"
    chest_wall: str = "sliding"
    fascia_stiffness: float = FASCIA_STIFFNESS
    constraints: str | None = None
    linear_solver: str = "auto"

    def __post_init__(self) -> None:
        self.materials = {
            name: m if isinstance(m, Material) else Material(**m)
            for name, m in self.materials.items()
        }
        for name, m in self.materials.items():
            m.check(name)
        if "skin" in self.materials and self.materials["skin"].elements is None:
            skin = self.materials["skin"]
            if skin.membrane is None:
                self.materials["skin"] = replace(skin, membrane=SKIN_THICKNESS)
        self.unloaded_gravity = tuple(float(v) for v in self.unloaded_gravity)
        self.compression_gravity = tuple(float(v) for v in self.compression_gravity)
        rules = {  # setting: (holds, what it must)
            "compression_ratio": (
                self.compression_ratio is None or 0 < self.compression_ratio < 1,
                "lie in (0, 1)",
            ),
            "unloaded_steps": (self.unloaded_steps >= 0, "be at least 0 (0: no unloaded state)"),
            "compression_steps": (self.compression_steps >= 1, "be at least 1"),
            "friction": (self.friction >= 0, "be >= 0 (0: frictionless)"),
            "fascia_stiffness": (self.fascia_stiffness >= 0, "be >= 0 Pa/mm (0: free sliding)"),
            "view": (self.view in VIEWS, f"be one of {VIEWS}"),
            "angle": (0 <= self.angle <= 90, "lie in [0, 90] degrees"),
            "averaging": (self.averaging in ("nodal", "element"), "be 'nodal' or 'element'"),
            "chest_wall": (self.chest_wall in CHEST_WALLS, f"be one of {CHEST_WALLS}"),
            "linear_solver": (self.linear_solver in BACKENDS, f"be one of {BACKENDS}"),
            "unloaded_gravity": (len(self.unloaded_gravity) == 3, "be 3 numbers (Pa/mm)"),
            "compression_gravity": (len(self.compression_gravity) == 3, "be 3 numbers (Pa/mm)"),
        }
        for key, (holds, rule) in rules.items():
            if not holds:
                raise ValueError(f"simulation.{key} must {rule}, got {getattr(self, key)!r}")
        self._schedule = None if self.plates is None else plate_schedule_from(self.plates)

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

    def schedule(self, traj: Trajectory, start: NDArray) -> PlateSchedule:
        """The plates for the shape ``start`` (N, 3): the configured ones, or the view's
        placed at first contact and moving to the target compression ratio."""
        if self._schedule is not None:
            return self._schedule
        ratio = self.target_ratio(traj)
        return plate_schedule(traj, start, None, self.view, self.angle, compression_ratio=ratio)

    def __call__(self, traj: Trajectory) -> Trajectory:
        """Simulate both steps; returns a copy of ``traj`` with its trajectories filled in.

        Raises
        ------
        SimulationFailed
            A step did not converge (the reason names the load factor and Newton's trouble).
        ValueError
            Bad input (missing material, no chest wall, no compression ratio, bad files).
        """
        source = traj.source
        if self._schedule is None:
            self.target_ratio(traj)
        held = (
            None if self.constraints is None else read_constraints(self.constraints, traj.n_nodes)
        )
        sets = {
            name: read_indices(m.elements, f"simulation.materials.{name}.elements")
            for name, m in self.materials.items()
            if m.elements is not None
        }
        options = dict(
            materials=self.materials,
            averaging=self.averaging,
            chest=self.chest_wall,
            fascia=self.fascia_stiffness,
            held=held,
            sets=sets,
            settings=replace(DEFAULT_NEWTON, linear_solver=self.linear_solver),
        )
        seconds: dict[str, float] = {}
        unloaded = np.zeros((0, traj.n_nodes, 3))
        if self.unloaded_steps:
            unloaded = _timed(
                "unloaded state",
                seconds,
                source,
                lambda: unloaded_state(
                    traj, n_steps=self.unloaded_steps, body_force=self.unloaded_gravity, **options
                ),
            )
        start = unloaded[-1] if len(unloaded) else traj.points
        schedule = self.schedule(traj, start)
        result = _timed(
            "compression",
            seconds,
            source,
            lambda: compression(
                traj,
                start,
                schedule,
                n_steps=self.compression_steps,
                body_force=self.compression_gravity,
                friction=self.friction,
                **options,
            ),
        )
        metadata = {
            **traj.metadata,
            "simulation": {
                "materials": {
                    k: {f: v for f, v in vars(m).items() if v is not None}
                    for k, m in self.materials.items()
                },
                "friction": self.friction,
                "view": self.view if self._schedule is None else "plates",
                "angle": self.angle,
                "unloaded_gravity": list(self.unloaded_gravity),
                "compression_gravity": list(self.compression_gravity),
                "averaging": self.averaging,
                "chest_wall": self.chest_wall,
                "fascia_stiffness": self.fascia_stiffness,
                "constraints": self.constraints,
                "linear_solver": self.linear_solver,
                "plate_extent_mm": [float(e) if np.isfinite(e) else None for e in schedule.extent],
                "compression_ratio": float(result.compression_ratio[-1]),
                "compressed_thickness_mm": schedule.gap(1.0),
                **shape_changes(traj.points, traj.cells, start, result.positions[-1]),
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
