"""Boundary conditions of a breast: the chest wall, a user's held directions, and the plates.

Chest wall (``chest_wall``; the reference paper: "the muscle as a non-deformable body ... in
the anteroposterior direction, we constrained the movement of nodes at the interface between
the muscle and other tissues"):

* ``sliding`` (default): the muscle's nodes are held (it does not deform); the nodes of the
  muscle/breast interface are held along the chest-wall normal (`chest_wall_normals`) and
  slide along the wall, resisted by the retromammary fascia (`ChestWallFascia`: a tangential
  stiffness per unit area of wall, ``FASCIA_STIFFNESS`` by default; 0 leaves only the muscle
  elements between them and the held muscle nodes, which on the cohort's one-element-thick
  muscle is nothing: under the standing gravity the breast slid down the wall by up to
  340 mm). A breast without muscle elements has nothing to slide on: its flat posterior
  cut (where a segmentation was cropped at the chest wall,
  `fem.contract.quality.posterior_cut`) is tied except its rim on the skin, which slides (so
  the plates, which reach back to the chest wall, move it).
* ``tied``: the muscle's nodes and the interface are held in all directions.
* ``anteroposterior``: the interface held along y only, the muscle deformable, plus two pins
  for the rigid-body modes this leaves (this project's first engine; kept to reproduce the
  committed paper cohort, whose compressions slide the chest-wall layer sideways).
* ``none``: only the user's held directions (``constraints``).

Plates: `PlateSchedule` moves two parallel rigid plates (`fem.engine.contact.RigidPlate`) from
their first contact to the compressed thickness, cranio-caudal (``cc``: normals +-z) or
mediolateral-oblique (``mlo``: the plates turned about the anteroposterior axis y by
``angle`` degrees, the lower plate, the detector, under the breast's lateral side).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from fem.contract.quality import boundary_faces, posterior_cut
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.assembly import assemble
from fem.engine.constraints import HeldDirections

AP_AXIS = 1  #: anteroposterior axis (y, RAS+)
#: Tangential stiffness of the retromammary fascia per unit area of chest wall, Pa/mm: a
#: layer of loose connective tissue 5 mm thick with the fat's shear modulus (1100 Pa / 3).
FASCIA_STIFFNESS = 75.0
CHEST_WALLS = ("sliding", "tied", "anteroposterior", "none")
VIEWS = ("cc", "mlo")
AXIS_LETTERS = {"x": 0, "y": 1, "z": 2}


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


def chest_wall_normals(points: NDArray) -> NDArray[np.float64]:
    """Unit normals (M, 3) of the chest wall through ``points`` (M, 3), mm.

    The wall is the least-squares quadric ``y = f(x, z)`` (a plane below six points) through
    the points; its normal ``(f_x, -1, f_z) / |.|`` points posteriorly. The mesh's own
    muscle/breast faces form a staircase at the element size whose normals scatter by up to
    90 deg; the fitted wall is as smooth as a torso.
    """
    x, y, z = points.T
    terms = [np.ones_like(x), x, z]
    if len(points) >= 6:
        terms += [x * x, x * z, z * z]
    coef, *_ = np.linalg.lstsq(np.stack(terms, axis=1), y, rcond=None)
    fx, fz = coef[1] + 0 * x, coef[2] + 0 * x
    if len(coef) == 6:
        fx, fz = fx + 2 * coef[3] * x + coef[4] * z, fz + coef[4] * x + 2 * coef[5] * z
    normals = np.stack([fx, -np.ones_like(x), fz], axis=1)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def sliding_wall(traj: Trajectory) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The ``sliding`` chest wall's nodes (module docstring): those that slide along the wall
    and those held in all directions (the muscle's, or a flat cut's inside), (M,) and (K,)."""
    wall = chest_wall_nodes(traj)
    muscle = np.unique(traj.cells[traj.tissue == Tissue.MUSCLE])
    sliding = wall
    if muscle.size == 0:  # a flat cut, no muscle to hold it: only its rim slides
        sliding = np.intersect1d(wall, traj.flagged(NodeFlag.SKIN))
    return sliding, np.setdiff1d(np.union1d(wall, muscle), sliding)


def chest_wall(
    traj: Trajectory, points: NDArray, mode: str = "sliding", translations: tuple[int, ...] = (0, 2)
) -> HeldDirections:
    """The held directions of the chest wall ``mode`` (module docstring) at ``points`` (N, 3),
    the shape the step starts from. ``translations``: the axes of the ``anteroposterior``
    mode's anchor pin (x and z for the unloaded state; x only under the plates, which hold z).

    Raises
    ------
    ValueError
        An unknown mode, or a mesh with no chest wall to hold.
    """
    if mode not in CHEST_WALLS:
        raise ValueError(f"simulation.chest_wall must be one of {CHEST_WALLS}, got {mode!r}")
    if mode == "none":
        return HeldDirections.none()
    wall = chest_wall_nodes(traj)
    if wall.size < 3:
        raise ValueError(
            f"{traj.source}: no muscle/breast interface nodes (field 'node_flags') and no flat "
            "posterior cut face: no chest wall to hold; give held nodes as "
            "simulation.constraints with simulation.chest_wall=none"
        )
    if mode == "anteroposterior":
        p = points[wall]
        anchor = wall[np.argmin(np.linalg.norm(p - p.mean(0), axis=1))]
        far = wall[np.argmax(np.abs(p[:, 2] - points[anchor, 2]))]
        return (
            HeldDirections.axes(wall, (AP_AXIS,))
            + HeldDirections.axes([anchor], translations)
            + HeldDirections.axes([far], (0,))
        )
    sliding, tied = sliding_wall(traj)
    if mode == "tied":
        return HeldDirections.axes(np.union1d(sliding, tied))
    return HeldDirections.axes(tied) + HeldDirections(sliding, chest_wall_normals(points[sliding]))


def wall_areas(traj: Trajectory, points: NDArray) -> NDArray[np.float64]:
    """Area of chest wall each node stands for, (N,) mm^2: a third of each adjacent triangle
    of the breast's boundary (its elements other than muscle) whose three nodes lie on the
    chest wall (`chest_wall_nodes`), at ``points`` (N, 3)."""
    breast = traj.cells[traj.tissue != Tissue.MUSCLE]
    faces, _ = boundary_faces(points, breast)
    on_wall = np.zeros(len(points), bool)
    on_wall[chest_wall_nodes(traj)] = True
    faces = faces[on_wall[faces].all(axis=1)]
    p = points[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return np.bincount(faces.ravel(), weights=np.repeat(area / 3, 3), minlength=len(points))


@dataclass
class ChestWallFascia:
    """The retromammary fascia under a sliding chest wall: each sliding node is held to where
    the step starts by a tangential spring, ``W = 1/2 sum_i k_i |P_i (x_i - a_i)|^2`` with
    ``P_i = I - n_i n_i^T``. A model part like the skin membrane (energy, force, tangent
    blocks); the node's normal direction is held by the chest wall's frame.

    Attributes
    ----------
    nodes : (M,) int64
        The sliding nodes.
    normals : (M, 3) float
        The chest-wall normal at each (`chest_wall_normals`).
    stiffness : (M,) float
        ``k_i``: the fascia's stiffness per unit area times the node's wall area, Pa mm.
    anchor : (M, 3) float
        ``a_i``: the node's position where the step starts, mm.
    n_nodes : int
        Nodes of the mesh.
    """

    nodes: NDArray[np.int64]
    normals: NDArray[np.float64]
    stiffness: NDArray[np.float64]
    anchor: NDArray[np.float64]
    n_nodes: int

    @property
    def dofs(self) -> NDArray[np.int64]:
        """The nodes' DOFs (M, 3)."""
        return 3 * self.nodes[:, None] + np.arange(3)

    def _projector(self) -> NDArray[np.float64]:
        return np.eye(3) - self.normals[:, :, None] * self.normals[:, None, :]  # (M, 3, 3)

    def _slip(self, x: NDArray) -> NDArray[np.float64]:
        d = x[self.nodes] - self.anchor
        return d - (d * self.normals).sum(axis=1, keepdims=True) * self.normals  # (M, 3)

    def energy(self, x: NDArray) -> float:
        """Stored energy, Pa mm^3."""
        return float(0.5 * self.stiffness @ (self._slip(x) ** 2).sum(axis=1))

    def internal_force(self, x: NDArray) -> NDArray[np.float64]:
        """``dW/dx`` (3N,), Pa mm^2."""
        f = np.zeros(3 * self.n_nodes)
        f[self.dofs] = self.stiffness[:, None] * self._slip(x)
        return f

    def tangent(self, x: NDArray) -> sparse.csr_matrix:
        """``d2W/dx2`` (3N, 3N), Pa mm."""
        return assemble(3 * self.n_nodes, self.dofs, self.tangent_blocks(x))

    def tangent_blocks(self, x: NDArray) -> NDArray[np.float64]:
        """Node blocks (M, 3, 3) ``k_i P_i`` of ``d2W/dx2`` over `dofs`, Pa mm."""
        return self.stiffness[:, None, None] * self._projector()


def chest_wall_fascia(
    traj: Trajectory, points: NDArray, mode: str, stiffness: float = FASCIA_STIFFNESS
) -> ChestWallFascia | None:
    """The fascia (`ChestWallFascia`) of the ``sliding`` chest wall on the shape ``points``
    (N, 3) where the step starts, with ``stiffness`` per unit area of wall (Pa/mm); None for
    another ``mode`` or a zero stiffness."""
    if mode != "sliding" or stiffness == 0:
        return None
    sliding, _ = sliding_wall(traj)
    k = stiffness * wall_areas(traj, points)[sliding]
    return ChestWallFascia(
        sliding, chest_wall_normals(points[sliding]), k, points[sliding].copy(), len(points)
    )


def read_constraints(path: str | Path, n_nodes: int) -> HeldDirections:
    """Held directions from a file: a text file with one node per line, ``<node> [axes]``
    (axes any of ``x``, ``y``, ``z``, e.g. ``17 xz``; none: all three), or a ``.npy`` array
    of node indices (all three axes held).

    Raises
    ------
    ValueError
        The file cannot be read, a line is malformed, a node is outside the mesh or an axis
        letter unknown; the message names the file and the line.
    """
    path = Path(path)
    rows: list[tuple[int, str]] = []
    try:
        if path.suffix == ".npy":
            nodes = np.atleast_1d(np.load(path, allow_pickle=False))
            if nodes.dtype.kind not in "iu":
                raise ValueError(f"holds {nodes.dtype} values, not node indices")
            rows = [(int(i), "xyz") for i in nodes.ravel()]
        else:
            for number, line in enumerate(path.read_text().splitlines(), 1):
                words = line.split("#")[0].split()
                if not words:
                    continue
                axes = words[1] if len(words) > 1 else "xyz"
                if len(words) > 2 or not words[0].lstrip("-").isdigit() or set(axes) - set("xyz"):
                    raise ValueError(f"line {number} {line!r} is not '<node> [axes from xyz]'")
                rows.append((int(words[0]), axes))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read held nodes (simulation.constraints): {exc}") from exc
    if not rows:
        raise ValueError(f"{path}: no held nodes (simulation.constraints)")
    nodes = np.array([i for i, _ in rows])
    if nodes.min() < 0 or nodes.max() >= n_nodes:
        raise ValueError(
            f"{path}: node indices must lie in [0, {n_nodes}) (simulation.constraints), got "
            f"[{nodes.min()}, {nodes.max()}]"
        )
    axes = [sorted({AXIS_LETTERS[a] for a in letters}) for _, letters in rows]
    return HeldDirections(np.repeat(nodes, [len(a) for a in axes]), np.eye(3)[np.concatenate(axes)])


def lower_plate_normal(view: str, angle_deg: float, laterality: str | None, source: str) -> NDArray:
    """Unit normal of the lower plate into the breast: +z (``cc``), or for ``mlo`` +z turned
    about y by ``angle_deg`` towards the medial side (the detector lies inferolateral).

    Raises
    ------
    ValueError
        An unknown view, or ``mlo`` without the breast's laterality.
    """
    if view not in VIEWS:
        raise ValueError(f"simulation.view must be one of {VIEWS}, got {view!r}")
    if view == "cc":
        return np.array([0.0, 0.0, 1.0])
    if laterality not in ("L", "R"):
        raise ValueError(
            f"{source}: the mlo view needs the breast's side: metadata field 'laterality' must "
            f"be 'L' or 'R', got {laterality!r}"
        )
    medial = -1.0 if laterality == "R" else 1.0  # RAS+: the right breast lies at +x
    a = np.radians(angle_deg)
    return np.array([medial * np.sin(a), 0.0, np.cos(a)])


@dataclass(frozen=True)
class PlateSchedule:
    """Two parallel rigid plates and their straight motion over the load factor s in [0, 1].

    Parameters
    ----------
    lower, upper : (3, 3) float
        Each plate at s = 0 as rows origin (a point on its chest-side edge, mm), unit normal
        into the breast, unit in-plane axis away from the chest (`RigidPlate`).
    lower_travel, upper_travel : (3,) float
        Displacement of each plate at s = 1, mm.
    extent : (2,) float
        Plate length along its axis and width across, mm (inf: unbounded).
    """

    lower: NDArray
    upper: NDArray
    lower_travel: NDArray = field(default_factory=lambda: np.zeros(3))
    upper_travel: NDArray = field(default_factory=lambda: np.zeros(3))
    extent: tuple[float, float] = (np.inf, np.inf)

    def frames(self, s: float | NDArray) -> NDArray[np.float64]:
        """Both plates (2, 3, 3) at load factor ``s``, or (T, 2, 3, 3) at each of ``s`` (T,)."""
        s = np.asarray(s, float)
        out = np.broadcast_to(np.stack([self.lower, self.upper]), (*s.shape, 2, 3, 3)).copy()
        travel = np.stack([np.asarray(self.lower_travel), np.asarray(self.upper_travel)])
        out[..., 0, :] += s[..., None, None] * travel  # (..., 2, 3) origins
        return out.astype(float)

    def gap(self, s: float | NDArray) -> float | NDArray[np.float64]:
        """Distance between the plates along the lower plate's normal at ``s`` (or each of
        ``s``), mm."""
        plates = self.frames(s)
        gap = np.einsum(
            "...i,...i->...", plates[..., 1, 0, :] - plates[..., 0, 0, :], plates[..., 0, 1, :]
        )
        return float(gap) if gap.ndim == 0 else gap

    def recorded(self, n_steps: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The plates (T, 2, 3, 3) and the compression ratio ``1 - gap(s) / gap(0)`` (T,) at
        the ``n_steps`` equally spaced recorded load factors ``k / n_steps``."""
        s = np.arange(1, n_steps + 1) / n_steps
        return self.frames(s), 1.0 - self.gap(s) / self.gap(0.0)


def skin_span(traj: Trajectory, start: NDArray, normal: NDArray) -> tuple[float, float]:
    """Lowest and highest skin node of the shape ``start`` (N, 3) along ``normal``, mm: where
    plates normal to it first touch the breast."""
    height = start[traj.flagged(NodeFlag.SKIN)] @ normal
    return float(height.min()), float(height.max())


def plate_schedule(
    traj: Trajectory,
    start: NDArray,
    compressed_thickness: float | None = None,
    view: str = "cc",
    angle: float = 45.0,
    compression_ratio: float | None = None,
) -> PlateSchedule:
    """The plates that compress the shape ``start`` (N, 3) of ``traj``'s mesh to
    ``compressed_thickness`` (mm), or to ``compression_ratio`` of the breast's extent along
    their normal, in the ``view``: the lower plate at the skin node lowest along its normal (the
    inframammary fold for cc), the upper one starting at the highest (first contact) and moving
    down to the thickness above it; both reach back to the most anterior chest-wall node (a
    rigid plate does not enter the torso).

    Raises
    ------
    ValueError
        The thickness is not positive or not below the breast's extent along the normal.
    """
    normal = lower_plate_normal(view, angle, traj.metadata.get("laterality"), traj.source)
    bottom, top = skin_span(traj, start, normal)
    if compression_ratio is not None:
        compressed_thickness = (1.0 - compression_ratio) * (top - bottom)
    if not 0 < compressed_thickness < top - bottom:
        along = (
            "cranio-caudal extent" if view == "cc" else f"extent along the {view} plates' normal"
        )
        raise ValueError(
            f"{traj.source}: compressed thickness {compressed_thickness:.1f} mm is not smaller "
            f"than the breast's {along} {top - bottom:.1f} mm (or not positive)"
        )
    wall = chest_wall_nodes(traj)
    edge = float(start[wall, AP_AXIS].max()) if wall.size else float(start[:, AP_AXIS].min())
    axis = np.array([0.0, 1.0, 0.0])
    lower = np.stack([edge * axis + bottom * normal, normal, axis])
    upper = np.stack([edge * axis + top * normal, -normal, axis])
    travel = -(top - bottom - compressed_thickness) * normal
    return PlateSchedule(lower, upper, upper_travel=travel)
