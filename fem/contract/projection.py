"""Projection of a shape onto physically valid ones: no inverted element, no node inside a plate,
the whole volume within bounds.

A shape that a surrogate predicts, or a finer mesh's answer sampled at a coarser mesh's nodes
(`fem.breasts.cohort_simulation.simulate_refined`), can turn a tetrahedron inside out or put
skin into a plate. `project_valid` moves the nodes as little as it can until every constraint
holds, by position-based constraint projection (Jacobi iterations, as in position-based
dynamics): each violated constraint ``C(x) >= 0`` asks its nodes for its minimum-norm linearised
correction ``dx = -C grad C / |grad C|^2``; a node's requests are averaged; plate constraints are
projected exactly, last in each sweep. Where neighbouring elements' requests cancel (a fold
of the mesh, typically against the held chest wall), the count of violated elements stops
falling; after `STALL_SWEEPS` such sweeps their nodes take one Laplacian smoothing step (each
towards the mean of its mesh neighbours, along the directions it may move in), which unfolds
the patch, and the sweeps go on.

* element volume: ``V_e(x) >= min_volume_ratio * V_e(reference)``, with
  ``dV/dx_a = (x_b - x_d) x (x_c - x_d) / 6``-type face normals (`volume_gradients`);
* plates: a skin node the plate covers (`fem.contract.plates.covered`) lies on the breast's
  side of it (`fem.contract.plates.penetration` <= 0);
* whole volume: ``V(x) / V(reference) - 1`` within ``volume_change`` (lower, upper), moving the
  boundary nodes along their area-weighted normals.

Pure NumPy; one sweep is a few vectorised passes over the elements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fem.contract.plates import NORMAL, covered, penetration
from fem.contract.quality import mesh_edges, signed_volume

#: Volume ratio asked of a violated element beyond ``min_volume_ratio`` (the linearised
#: correction undershoots a cubic constraint; aiming past it converges in fewer sweeps).
OVERSHOOT = 1.5

#: Distance from a plate within which a node counts as on it, mm.
ON_PLATE = 1e-9

#: Sweeps without fewer violated elements after which their nodes are smoothed (a stall).
STALL_SWEEPS = 50


@dataclass(frozen=True)
class Projection:
    """A projected shape and what the projection did.

    Attributes
    ----------
    points : (N, 3) float64
        The valid shape, mm.
    sweeps : int
        Jacobi sweeps done (0: the shape was valid).
    moved_rms_mm, moved_max_mm : float
        RMS and largest node displacement from the input shape, mm.
    min_volume_ratio : float
        Smallest ``V_e / V_e(reference)`` of the result.
    volume_change : float
        ``V / V(reference) - 1`` of the result.
    max_penetration_mm : float
        Deepest skin node inside a plate covering it, mm (<= ``tolerance_mm``).
    """

    points: NDArray[np.float64]
    sweeps: int
    moved_rms_mm: float
    moved_max_mm: float
    min_volume_ratio: float
    volume_change: float
    max_penetration_mm: float


class ProjectionFailed(RuntimeError):
    """The constraints still do not hold after the allowed sweeps."""


def volume_gradients(points: NDArray, cells: NDArray) -> NDArray[np.float64]:
    """``dV_e / dx_a`` of each tetrahedron's signed volume, (E, 4, 3), mm^2.

    The gradient at a vertex is the opposite face's area vector over three, pointing from that
    face towards the vertex: moving the vertex along it grows the volume.
    """
    p = points[cells]  # (E, 4, 3)
    g = np.empty_like(p)
    g[:, 1] = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]) / 6.0
    g[:, 2] = np.cross(p[:, 3] - p[:, 0], p[:, 1] - p[:, 0]) / 6.0
    g[:, 3] = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) / 6.0
    g[:, 0] = -g[:, 1:].sum(axis=1)
    return g


def plate_depth(points: NDArray, skin: NDArray, plates: NDArray) -> NDArray[np.float64]:
    """Depth of each skin node inside each plate covering it, (2, S) mm (0 when not)."""
    p = points[skin]
    return np.stack(
        [
            np.where(covered(p, plate), np.maximum(penetration(p, plate), 0.0), 0.0)
            for plate in plates
        ]
    )


@dataclass(frozen=True)
class Constraints:
    """What a valid shape of a mesh satisfies, computed once from its reference shape
    (`constraints`) for all the shapes projected against it (`project`, `project_steps`).

    Attributes
    ----------
    cells : (E, 4) int64
    reference : (N, 3) float64
        Stress-free shape, mm.
    volume : (E,) float64
        Element volumes of ``reference``, mm^3.
    target : (E,) float64
        Smallest accepted element volumes, mm^3.
    size : (E,) float64
        Edge of a regular tetrahedron of each reference volume, mm: the longest step an
        element asks of a vertex.
    free : (N, 3, 3) float64
        Per node, the projector onto the directions it may move in (`free_projectors`).
    edges : (2, 2M) int64
        The mesh's directed edges (`fem.contract.quality.mesh_edges`): the neighbours a
        stalled patch is smoothed towards.
    skin : (S,) int64 or None
        Nodes held outside the plates.
    volume_change : (float, float) or None
        Accepted range of the whole volume's change.
    tolerance_mm : float
        Plate penetration accepted, mm.
    max_sweeps : int
        Jacobi sweeps before giving up.
    min_volume_ratio : float
        ``target / volume``.
    """

    cells: NDArray[np.int64]
    reference: NDArray[np.float64]
    volume: NDArray[np.float64]
    target: NDArray[np.float64]
    size: NDArray[np.float64]
    free: NDArray[np.float64]
    edges: NDArray[np.int64]
    skin: NDArray[np.int64] | None
    volume_change: tuple[float, float] | None
    tolerance_mm: float
    max_sweeps: int
    min_volume_ratio: float

    def held(self, points: NDArray) -> NDArray[np.float64]:
        """``points`` (..., N, 3) with their displacement along the held directions removed."""
        return self.reference + np.einsum("nij,...nj->...ni", self.free, points - self.reference)

    def measure(
        self, x: NDArray, plates: NDArray | None
    ) -> tuple[NDArray, float, NDArray | None, float]:
        """Element volumes (E,), whole-volume change, plate contact (`_plate_contact`) and the
        deepest skin node inside a plate (mm) of the shape ``x`` (N, 3)."""
        volume = signed_volume(x, self.cells)
        total = volume.sum() / self.volume.sum() - 1.0
        walls, deep = _plate_contact(x, self.skin, plates) if plates is not None else (None, 0.0)
        return volume, float(total), walls, deep

    def off_volume(self, total: float) -> bool:
        """Whether a whole-volume change ``total`` lies outside the accepted range."""
        return self.volume_change is not None and not (
            self.volume_change[0] <= total <= self.volume_change[1]
        )


def constraints(
    cells: NDArray,
    reference: NDArray,
    skin: NDArray | None = None,
    min_volume_ratio: float = 0.1,
    volume_change: tuple[float, float] | None = None,
    held: tuple[NDArray, NDArray] | None = None,
    tolerance_mm: float = 1e-6,
    max_sweeps: int = 2000,
) -> Constraints:
    """The constraints of valid shapes of a mesh (arguments as `project_valid`'s).

    Raises
    ------
    ValueError
        A reference element that is not right-handed, or a setting out of range.
    """
    cells = np.asarray(cells, np.int64)
    reference = np.asarray(reference, np.float64)
    if reference.ndim != 2 or reference.shape[1] != 3:
        raise ValueError(f"reference must be (N, 3), got {reference.shape}")
    if not 0 < min_volume_ratio < 1:
        raise ValueError(f"min_volume_ratio must lie in (0, 1), got {min_volume_ratio!r}")
    if volume_change is not None and not volume_change[0] < volume_change[1]:
        raise ValueError(f"volume_change must be (lower, upper), got {volume_change!r}")
    volume = signed_volume(reference, cells)
    if (volume <= 0).any():
        raise ValueError(f"{int((volume <= 0).sum())} reference elements are not right-handed")
    return Constraints(
        cells=cells,
        reference=reference,
        volume=volume,
        target=min_volume_ratio * volume,
        size=np.cbrt(6 * np.sqrt(2) * volume),
        free=free_projectors(len(reference), held),
        edges=mesh_edges(cells),
        skin=None if skin is None else np.asarray(skin, np.int64),
        volume_change=volume_change,
        tolerance_mm=tolerance_mm,
        max_sweeps=max_sweeps,
        min_volume_ratio=min_volume_ratio,
    )


def project(c: Constraints, points: NDArray, plates: NDArray | None = None) -> Projection:
    """The shape ``points`` (N, 3) moved as little as position-based projection can until it
    satisfies ``c`` (with ``plates`` (2, 3, 3) when ``c`` has skin nodes): the held directions
    first, then Jacobi sweeps.

    Raises
    ------
    ValueError
        ``points`` of another shape than the reference, or plates without skin nodes.
    ProjectionFailed
        Some constraint still fails after ``c.max_sweeps`` sweeps.
    """
    x0 = np.asarray(points, np.float64)
    if x0.shape != c.reference.shape:
        raise ValueError(f"points {x0.shape} and reference {c.reference.shape} must both be (N, 3)")
    if (plates is None) != (c.skin is None):
        raise ValueError("plates and skin go together")
    x = c.held(x0)  # held as in ``reference``
    sweeps, fewest, stalled = 0, np.inf, 0
    for sweeps in range(c.max_sweeps + 1):
        volume, total, walls, deep = c.measure(x, plates)
        bad = volume < c.target
        off_volume = c.off_volume(total)
        if not bad.any() and not off_volume and deep <= c.tolerance_mm:
            break
        if sweeps == c.max_sweeps:
            raise ProjectionFailed(
                f"after {c.max_sweeps} sweeps: {int(bad.sum())} elements below volume ratio "
                f"{c.min_volume_ratio:g}, volume change {100 * total:+.2f} %, "
                f"{deep:.3g} mm inside a plate"
            )
        fewest, stalled = (bad.sum(), 0) if bad.sum() < fewest else (fewest, stalled + 1)
        if stalled >= STALL_SWEEPS:  # requests that cancel: unfold the patch
            x = _smoothing_step(x, c.edges, np.unique(c.cells[bad]), c.free)
            fewest, stalled = np.inf, 0
        else:
            deficit = OVERSHOOT * c.target[bad] - volume[bad]
            x = _element_sweep(x, c.cells, bad, deficit, c.size[bad], c.free, walls)
        if off_volume:
            lower, upper = c.volume_change
            margin = 0.1 * (upper - lower)  # aim inside: the linearised step lands near it
            goal = (1.0 + np.clip(total, lower + margin, upper - margin)) * c.volume.sum()
            deficit = goal - signed_volume(x, c.cells).sum()
            x = _whole_volume_step(x, c.cells, deficit, float(np.median(c.size)), c.free)
        if plates is not None:
            x = _plate_step(x, c.skin, plates)
    return _projection(x0, x, sweeps, volume, c.volume, total, deep)


def _projection(
    x0: NDArray, x: NDArray, sweeps: int, volume: NDArray, v_ref: NDArray, total: float, deep: float
) -> Projection:
    moved = np.linalg.norm(x - x0, axis=-1)
    return Projection(
        points=x,
        sweeps=sweeps,
        moved_rms_mm=float(np.sqrt(np.mean(moved**2))),
        moved_max_mm=float(moved.max(initial=0.0)),
        min_volume_ratio=float((volume / v_ref).min()),
        volume_change=float(total),
        max_penetration_mm=float(deep),
    )


def project_valid(
    cells: NDArray,
    reference: NDArray,
    points: NDArray,
    skin: NDArray | None = None,
    plates: NDArray | None = None,
    min_volume_ratio: float = 0.1,
    volume_change: tuple[float, float] | None = None,
    held: tuple[NDArray, NDArray] | None = None,
    tolerance_mm: float = 1e-6,
    max_sweeps: int = 2000,
) -> Projection:
    """The shape ``points`` moved as little as position-based projection can until it is valid.

    Parameters
    ----------
    cells : (E, 4) int
        Tetrahedra, right-handed in ``reference``.
    reference : (N, 3) float
        Stress-free shape, mm: each element's volume ratio and the whole volume's change are
        measured against it.
    points : (N, 3) float
        The shape to project, mm.
    skin : (S,) int, optional
        Nodes held outside the plates.
    plates : (2, 3, 3) float, optional
        Frames (origin, normal, axis) of the lower and the upper plate (`fem.contract.plates`).
    min_volume_ratio : float
        Smallest accepted ``V_e / V_e(reference)`` (> 0).
    volume_change : (float, float), optional
        Accepted range of ``V / V(reference) - 1`` of the whole mesh (e.g. the FE's own change
        +- 1 %); None: not constrained.
    held : ((M,) int, (M, 3) float), optional
        Directions along which nodes do not move from ``reference``, one row per node and
        unit direction (`fem.engine.constraints.HeldDirections`' rows: a chest wall's
        interface nodes held along its normal, its muscle nodes along all three axes); the
        input's displacement along them is removed first, as the FE holds them.
    tolerance_mm : float
        Plate penetration accepted, mm.
    max_sweeps : int
        Jacobi sweeps before giving up.

    Returns
    -------
    Projection

    Raises
    ------
    ValueError
        Inconsistent shapes or settings.
    ProjectionFailed
        Some constraint still fails after ``max_sweeps`` sweeps.
    """
    c = constraints(
        cells, reference, skin, min_volume_ratio, volume_change, held, tolerance_mm, max_sweeps
    )
    return project(c, points, plates)


@dataclass(frozen=True)
class StepProjections:
    """Every step of a trajectory projected (`project_steps`).

    Attributes
    ----------
    points : (T, N, 3) float64
        The valid shapes, mm; a failed step's is its input (held directions removed).
    sweeps : (T,) int
        Jacobi sweeps per step (0: valid once the held directions were removed).
    moved_rms_mm, moved_max_mm : (T,) float
        RMS and largest node displacement from the input, mm.
    min_volume_ratio : (T,) float
        Smallest ``V_e / V_e(reference)`` per step.
    failed : dict[int, str]
        The steps no valid shape was found for, with why.
    """

    points: NDArray[np.float64]
    sweeps: NDArray[np.int64]
    moved_rms_mm: NDArray[np.float64]
    moved_max_mm: NDArray[np.float64]
    min_volume_ratio: NDArray[np.float64]
    failed: dict[int, str]


def project_steps(c: Constraints, steps: NDArray, plates: NDArray | None = None) -> StepProjections:
    """Every shape of ``steps`` (T, N, 3) projected onto ``c`` (with the plates of each step,
    ``plates`` (T, 2, 3, 3), when ``c`` has skin nodes).

    The held directions are removed from all steps at once and every step's constraints
    measured in one vectorised pass; only the steps still invalid then run `project`'s
    sweeps, so a trajectory that is valid but for its held directions costs a few array
    passes, not a loop of sweeps.
    """
    x0 = np.asarray(steps, np.float64)
    if x0.ndim != 3 or x0.shape[1:] != c.reference.shape:
        raise ValueError(f"steps {x0.shape} must be (T, {len(c.reference)}, 3)")
    if (plates is None) != (c.skin is None):
        raise ValueError("plates and skin go together")
    x = c.held(x0)
    volume = signed_volume(x, c.cells)  # (T, E)
    total = volume.sum(axis=1) / c.volume.sum() - 1.0
    deep = (
        np.array(
            [plate_depth(xt, c.skin, p).max(initial=0.0) for xt, p in zip(x, plates, strict=True)]
        )
        if plates is not None
        else np.zeros(len(x))
    )
    sweeps = np.zeros(len(x), np.int64)
    failed: dict[int, str] = {}
    ratio = (volume / c.volume).min(axis=1)
    for t in range(len(x)):
        if (
            (volume[t] >= c.target).all()
            and not c.off_volume(total[t])
            and deep[t] <= c.tolerance_mm
        ):
            continue
        try:
            p = project(c, x[t], None if plates is None else plates[t])
        except ProjectionFailed as exc:
            failed[t] = str(exc)
            continue
        x[t], sweeps[t], ratio[t] = p.points, p.sweeps, p.min_volume_ratio
    moved = np.linalg.norm(x - x0, axis=-1)  # (T, N)
    return StepProjections(
        points=x,
        sweeps=sweeps,
        moved_rms_mm=np.sqrt(np.mean(moved**2, axis=1)),
        moved_max_mm=moved.max(axis=1, initial=0.0),
        min_volume_ratio=ratio,
        failed=failed,
    )


def _plate_contact(x: NDArray, skin: NDArray, plates: NDArray) -> tuple[NDArray[np.float64], float]:
    """Per plate, the normal (into the breast) at each node lying on it, zero elsewhere
    (2, N, 3), and the deepest skin node inside a plate covering it, mm."""
    walls, deep = np.zeros((len(plates), len(x), 3)), 0.0
    p = x[skin]
    for k, plate in enumerate(plates):
        depth = np.where(covered(p, plate), penetration(p, plate), -np.inf)
        walls[k, skin[depth >= -ON_PLATE]] = plate[NORMAL]
        deep = max(deep, float(depth.max(initial=0.0)))
    return walls, deep


def free_projectors(n: int, held: tuple[NDArray, NDArray] | None) -> NDArray[np.float64]:
    """Per node, the orthogonal projector onto the directions it may move in (the complement
    of the span of its held directions), (N, 3, 3)."""
    span = np.zeros((n, 3, 3))
    if held is not None:
        nodes, directions = np.asarray(held[0], np.int64), np.asarray(held[1], np.float64)
        np.add.at(span, nodes, directions[:, :, None] * directions[:, None, :])
    values, vectors = np.linalg.eigh(span)
    vectors = vectors * (values <= 1e-9)[:, None, :]  # the eigenvectors no held direction spans
    return vectors @ np.swapaxes(vectors, 1, 2)


def _element_sweep(
    x: NDArray,
    cells: NDArray,
    bad: NDArray,
    deficit: NDArray,
    size: NDArray,
    free: NDArray,
    walls: NDArray | None = None,
) -> NDArray[np.float64]:
    """One Jacobi pass over the elements ``bad``: each asks ``deficit`` (B,) mm^3 more volume
    of its vertices, along the directions they may move in (``free``: `free_projectors`), at
    most its ``size`` (B,) mm per vertex (a nearly flat element's linearised request can be
    unbounded); a node takes the mean of its requests. A vertex on a plate (``walls``:
    `_plate_contact`) is not asked to move into it: the gradient's component into the plate is
    dropped, so the other vertices make the volume."""
    nodes = cells[bad]
    g = np.einsum("eaij,eaj->eai", free[nodes], volume_gradients(x, nodes))  # (B, 4, 3)
    for normals in () if walls is None else walls:
        n = normals[nodes]  # (B, 4, 3), zero off the plate
        into = np.minimum(np.einsum("eaj,eaj->ea", g, n), 0.0)
        g -= into[:, :, None] * n
    norm2 = np.einsum("eaj,eaj->e", g, g)
    step = (deficit / np.maximum(norm2, 1e-30))[:, None, None] * g
    length = np.linalg.norm(step, axis=2, keepdims=True)  # (B, 4, 1)
    step *= np.minimum(1.0, size[:, None, None] / np.maximum(length, 1e-30))
    out = np.zeros_like(x)
    np.add.at(out, nodes.ravel(), step.reshape(-1, 3))
    count = np.bincount(nodes.ravel(), minlength=len(x))
    return x + out / np.maximum(count, 1)[:, None]


def _smoothing_step(x: NDArray, edges: NDArray, nodes: NDArray, free: NDArray) -> NDArray:
    """One Laplacian smoothing step of ``nodes`` (K,): each moves to the mean of its mesh
    neighbours (``edges`` (2, 2M)), along the directions it may move in (``free``)."""
    source, target = edges
    mine = np.isin(target, nodes)
    total = np.zeros_like(x)
    np.add.at(total, target[mine], x[source[mine]])
    count = np.bincount(target[mine], minlength=len(x))[nodes]
    x = x.copy()
    x[nodes] += np.einsum("nij,nj->ni", free[nodes], total[nodes] / count[:, None] - x[nodes])
    return x


def _whole_volume_step(
    x: NDArray, cells: NDArray, deficit: float, size: float, free: NDArray
) -> NDArray[np.float64]:
    """The minimum-norm linearised step that adds ``deficit`` mm^3 to the whole volume: the
    nodes along the sum of their elements' volume gradients (interior nodes' cancel), in the
    directions they may move in, at most ``size`` mm per node."""
    g = np.zeros_like(x)
    np.add.at(g, cells.ravel(), volume_gradients(x, cells).reshape(-1, 3))
    g = np.einsum("nij,nj->ni", free, g)
    step = deficit / max(float(np.einsum("ij,ij->", g, g)), 1e-30) * g
    longest = float(np.linalg.norm(step, axis=1).max(initial=0.0))
    return x + step * min(1.0, size / max(longest, 1e-30))


def _plate_step(x: NDArray, skin: NDArray, plates: NDArray) -> NDArray:
    """Skin nodes inside a plate covering them moved onto its surface, along its normal."""
    x = x.copy()
    for plate, depth in zip(plates, plate_depth(x, skin, plates), strict=True):
        x[skin] += depth[:, None] * plate[NORMAL]
    return x
