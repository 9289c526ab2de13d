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
  side of it (`fem.contract.plates.penetration` <= 0); one inside leaves by the nearer face,
  the plate's surface or its chest-side edge face (`_plate_step`);
* whole volume: ``V(x) / V(reference) - 1`` within ``volume_change`` (lower, upper), moving the
  boundary nodes along their area-weighted normals.

Pure NumPy. The shapes of a trajectory (`project_steps`; `project` is the case of one shape)
sweep together, each with its own plates and its own sweep count and stall counter: one sweep
is a few vectorised passes over the (shape, violated element) pairs of all the shapes still
invalid, and a shape leaves the sweeps as soon as it is valid, so each shape goes through the
same operations as alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fem.contract.plates import AXIS, NORMAL, ORIGIN
from fem.contract.quality import mesh_edges, signed_volume

#: Volume ratio asked of a violated element beyond ``min_volume_ratio`` (the linearised
#: correction undershoots a cubic constraint; aiming past it converges in fewer sweeps).
OVERSHOOT = 1.5

#: Distance from a plate within which a node counts as on it, mm.
ON_PLATE = 1e-9

#: Distance behind a plate's chest-side edge face at which a skin node that leaves the plate
#: through that face is put, mm (`_plate_step`): past the float32 rounding of the written shapes
#: (3e-5 mm at 256 mm), so that a written shape's node is not covered by the plate again.
EDGE_CLEARANCE = 1e-3

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
    """``dV_e / dx_a`` of each tetrahedron's signed volume, (..., E, 4, 3), mm^2, of the shapes
    ``points`` (..., N, 3).

    The gradient at a vertex is the opposite face's area vector over three, pointing from that
    face towards the vertex: moving the vertex along it grows the volume.
    """
    p = points[..., cells, :]  # (..., E, 4, 3)
    g = np.empty_like(p)
    g[..., 1, :] = np.cross(p[..., 2, :] - p[..., 0, :], p[..., 3, :] - p[..., 0, :]) / 6.0
    g[..., 2, :] = np.cross(p[..., 3, :] - p[..., 0, :], p[..., 1, :] - p[..., 0, :]) / 6.0
    g[..., 3, :] = np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]) / 6.0
    g[..., 0, :] = -g[..., 1:, :].sum(axis=-2)
    return g


def plate_coordinates(
    points: NDArray, plates: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where the points lie relative to each plate, for several shapes with their own plates.

    Parameters
    ----------
    points : (..., K, 3) float
        Positions, mm.
    plates : (..., P, 3, 3) float
        Plate frames (`fem.contract.plates`), the leading axes as ``points``'.

    Returns
    -------
    along : (..., P, K) float64
        ``(p - origin) . axis``, mm: the plate covers the point when >= 0
        (`fem.contract.plates.covered`).
    depth : (..., P, K) float64
        ``-(p - origin) . normal``, mm: inside the plate when > 0
        (`fem.contract.plates.penetration`).
    """
    points, plates = np.asarray(points, np.float64), np.asarray(plates, np.float64)
    rel = points[..., None, :, :] - plates[..., :, None, ORIGIN, :]  # (..., P, K, 3)
    along = np.einsum("...pkj,...pj->...pk", rel, plates[..., AXIS, :])
    depth = -np.einsum("...pkj,...pj->...pk", rel, plates[..., NORMAL, :])
    return along, depth


def plate_depth(points: NDArray, skin: NDArray, plates: NDArray) -> NDArray[np.float64]:
    """Depth of each skin node inside each plate covering it, (..., 2, S) mm (0 when not), of
    the shapes ``points`` (..., N, 3) with their plates (..., 2, 3, 3)."""
    along, depth = plate_coordinates(points[..., skin, :], plates)
    return np.where(along >= 0, np.maximum(depth, 0.0), 0.0)


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
    limited : (L,) int64
        The nodes with a held direction (whose ``free`` is not the identity).
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
    limited: NDArray[np.int64]
    edges: NDArray[np.int64]
    skin: NDArray[np.int64] | None
    volume_change: tuple[float, float] | None
    tolerance_mm: float
    max_sweeps: int
    min_volume_ratio: float

    def held(self, points: NDArray) -> NDArray[np.float64]:
        """``points`` (..., N, 3) with their displacement along the held directions removed
        (a copy; only the `limited` nodes change)."""
        x, k = np.array(points, np.float64), self.limited
        x[..., k, :] = self.reference[k] + np.einsum(
            "nij,...nj->...ni", self.free[k], x[..., k, :] - self.reference[k]
        )
        return x

    def measure(
        self, x: NDArray, plates: NDArray | None, volume: NDArray | None = None
    ) -> tuple[NDArray, NDArray, NDArray | None, NDArray]:
        """What the constraints see of the shapes ``x`` (..., N, 3), with their ``plates``
        (..., 2, 3, 3) when there are skin nodes (and their element ``volume`` (..., E), mm^3,
        when already known: `_moved_volumes`).

        Returns
        -------
        volume : (..., E) float64
            Element volumes, mm^3.
        total : (...) float64
            Whole-volume change ``V / V(reference) - 1``.
        contact : (..., 2, N) bool or None
            Per plate, the skin nodes it covers lying on it or inside it (within `ON_PLATE`).
        deep : (...) float64
            The deepest skin node inside a plate covering it, mm (0 when none).
        """
        volume = signed_volume(x, self.cells) if volume is None else volume
        total = volume.sum(axis=-1) / self.volume.sum() - 1.0
        if plates is None:
            return volume, total, None, np.zeros(total.shape)
        along, depth = plate_coordinates(x[..., self.skin, :], plates)
        depth = np.where(along >= 0, depth, -np.inf)  # (..., 2, S): -inf where not covered
        contact = np.zeros((*depth.shape[:-1], x.shape[-2]), bool)
        contact[..., self.skin] = depth >= -ON_PLATE
        deep = depth.max(axis=(-2, -1), initial=0.0) + 0.0  # + 0: on a plate is 0, not -0
        return volume, total, contact, deep

    def off_volume(self, total: ArrayLike) -> NDArray[np.bool_]:
        """Whether each whole-volume change ``total`` (...) lies outside the accepted range."""
        total = np.asarray(total)
        if self.volume_change is None:
            return np.zeros(total.shape, bool)
        lower, upper = self.volume_change
        return ~((lower <= total) & (total <= upper))


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
    free = free_projectors(len(reference), held)
    return Constraints(
        cells=cells,
        reference=reference,
        volume=volume,
        target=min_volume_ratio * volume,
        size=np.cbrt(6 * np.sqrt(2) * volume),
        free=free,
        limited=np.flatnonzero(np.abs(free - np.eye(3)).max(axis=(1, 2), initial=0.0) > 0),
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
    first, then Jacobi sweeps (`project_steps`' with one step).

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
    out = project_steps(c, x0[None], None if plates is None else np.asarray(plates)[None])
    if out.failed:
        raise ProjectionFailed(out.failed[0])
    return Projection(
        points=out.points[0],
        sweeps=int(out.sweeps[0]),
        moved_rms_mm=float(out.moved_rms_mm[0]),
        moved_max_mm=float(out.moved_max_mm[0]),
        min_volume_ratio=float(out.min_volume_ratio[0]),
        volume_change=float(out.volume_change[0]),
        max_penetration_mm=float(out.max_penetration_mm[0]),
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
    min_volume_ratio, volume_change, max_penetration_mm : (T,) float
        Smallest ``V_e / V_e(reference)``, ``V / V(reference) - 1`` and deepest skin node
        inside a plate (mm) of each step (a failed step's: its input's).
    failed : dict[int, str]
        The steps no valid shape was found for, with why.
    """

    points: NDArray[np.float64]
    sweeps: NDArray[np.int64]
    moved_rms_mm: NDArray[np.float64]
    moved_max_mm: NDArray[np.float64]
    min_volume_ratio: NDArray[np.float64]
    volume_change: NDArray[np.float64]
    max_penetration_mm: NDArray[np.float64]
    failed: dict[int, str]


def project_steps(c: Constraints, steps: NDArray, plates: NDArray | None = None) -> StepProjections:
    """Every shape of ``steps`` (T, N, 3) projected onto ``c`` (with the plates of each step,
    ``plates`` (T, 2, 3, 3), when ``c`` has skin nodes), as `project` projects each alone.

    The held directions are removed from all steps at once and every step's constraints
    measured in one vectorised pass; the steps still invalid then sweep together
    (`_jacobi_sweeps`): a trajectory takes as many passes as its slowest step has sweeps, each
    over the violated elements of all the steps still invalid.
    """
    x0 = np.asarray(steps, np.float64)
    if x0.ndim != 3 or x0.shape[1:] != c.reference.shape:
        raise ValueError(f"steps {x0.shape} must be (T, {len(c.reference)}, 3)")
    if (plates is None) != (c.skin is None):
        raise ValueError("plates and skin go together")
    return _jacobi_sweeps(c, x0, None if plates is None else np.asarray(plates, np.float64))


def _jacobi_sweeps(c: Constraints, x0: NDArray, plates: NDArray | None) -> StepProjections:
    """The shapes ``x0`` (T, N, 3), held directions removed, in Jacobi sweeps, each with its own
    ``plates`` (T, 2, 3, 3) (None when ``c`` has no skin nodes), until it satisfies ``c``.

    Every sweep measures the shapes still invalid and moves them all (`_sweep`); a shape leaves
    as soon as it is valid, or after ``c.max_sweeps`` sweeps as failed. Each shape keeps its
    own stall count: after `STALL_SWEEPS` sweeps without fewer violated elements it takes a
    smoothing step instead of the elements' requests, as it would alone.
    """
    x = c.held(x0)
    volume, total, contact, deep = c.measure(x, plates)
    sweeps = np.zeros(len(x), np.int64)
    ratio, change, deepest = (volume / c.volume).min(axis=1), total.copy(), deep.copy()
    failed: dict[int, str] = {}
    out = x.copy()
    active, y, p = np.arange(len(x)), x, plates  # the shapes still sweeping: index, shape, plates
    before = y  # their shapes before the last sweep
    fewest, stalled = np.full(len(x), np.inf), np.zeros(len(x), np.int64)
    for sweep in range(c.max_sweeps + 1):
        if sweep:  # only the elements the sweep moved change volume
            volume, total, contact, deep = c.measure(
                y, p, _moved_volumes(c.cells, y, before, volume)
            )
        bad = volume < c.target  # (S, E)
        off = c.off_volume(total)
        valid = ~bad.any(axis=1) & ~off & (deep <= c.tolerance_mm)
        done = active[valid]
        out[done], sweeps[done], ratio[done] = y[valid], sweep, (volume[valid] / c.volume).min(1)
        change[done], deepest[done] = total[valid], deep[valid]
        if sweep == c.max_sweeps:
            for i in np.flatnonzero(~valid):
                failed[int(active[i])] = (
                    f"after {c.max_sweeps} sweeps: {int(bad[i].sum())} elements below volume "
                    f"ratio {c.min_volume_ratio:g}, volume change {100 * total[i]:+.2f} %, "
                    f"{deep[i]:.3g} mm inside a plate"
                )
            break
        if valid.any():
            keep = ~valid
            active, y, volume, total, bad, off = (
                a[keep] for a in (active, y, volume, total, bad, off)
            )
            fewest, stalled = fewest[keep], stalled[keep]
            p, contact = (None, None) if p is None else (p[keep], contact[keep])
        if not len(active):
            break
        count = bad.sum(axis=1)
        fewer = count < fewest
        fewest, stalled = np.where(fewer, count, fewest), np.where(fewer, 0, stalled + 1)
        stall = stalled >= STALL_SWEEPS  # requests that cancel: unfold the patch
        before, y = y, _sweep(c, y, p, volume, total, contact, bad, off, stall)
        fewest[stall], stalled[stall] = np.inf, 0
    moved = np.linalg.norm(out - x0, axis=-1)  # (T, N)
    return StepProjections(
        points=out,
        sweeps=sweeps,
        moved_rms_mm=np.sqrt(np.mean(moved**2, axis=1)),
        moved_max_mm=moved.max(axis=1, initial=0.0),
        min_volume_ratio=ratio,
        volume_change=change,
        max_penetration_mm=deepest,
        failed=failed,
    )


def _sweep(
    c: Constraints,
    x: NDArray,
    plates: NDArray | None,
    volume: NDArray,
    total: NDArray,
    contact: NDArray | None,
    bad: NDArray,
    off: NDArray,
    stall: NDArray,
) -> NDArray[np.float64]:
    """One Jacobi sweep of the shapes ``x`` (S, N, 3), as measured (`Constraints.measure`:
    ``volume``, ``total``, ``contact``; ``bad`` (S, E) their elements below the target,
    ``off`` (S,) those outside the volume range): the violated elements' requests, or for the
    shapes that ``stall`` (S,) one smoothing step of those elements' nodes; then the whole
    volume of the shapes ``off``; then the plates."""
    measured, pushed = x, bad & ~stall[:, None]
    step, element = np.nonzero(pushed)
    deficit = OVERSHOOT * c.target[element] - volume[step, element]
    x = _element_sweep(x, c.cells, pushed, deficit, c.size[element], c.free, contact, plates)
    if stall.any():
        nodes = np.zeros((int(stall.sum()), x.shape[1]), bool)
        step, element = np.nonzero(bad[stall])
        nodes[step[:, None], c.cells[element]] = True
        x[stall] = _smoothing_step(x[stall], c.edges, nodes, c.free)
    if off.any():
        lower, upper = c.volume_change
        margin = 0.1 * (upper - lower)  # aim inside: the linearised step lands near it
        goal = (1.0 + np.clip(total[off], lower + margin, upper - margin)) * c.volume.sum()
        deficit = goal - _moved_volumes(c.cells, x[off], measured[off], volume[off]).sum(axis=1)
        x[off] = _whole_volume_step(x[off], c.cells, deficit, float(np.median(c.size)), c.free)
    if plates is not None:
        x = _plate_step(x, c.skin, plates)
    return x


def _moved_volumes(
    cells: NDArray, x: NDArray, before: NDArray, volume: NDArray
) -> NDArray[np.float64]:
    """Element volumes (S, E) of the shapes ``x`` (S, N, 3), mm^3, from ``volume`` (S, E) of
    the shapes ``before`` (S, N, 3): `fem.contract.quality.signed_volume` of only the elements
    with a node that moved, the others' as they were (the same numbers as all recomputed)."""
    other = x != before
    moved = other[..., 0] | other[..., 1] | other[..., 2]  # (S, N)
    touched = moved[:, cells[:, 0]] | moved[:, cells[:, 1]]
    touched |= moved[:, cells[:, 2]] | moved[:, cells[:, 3]]  # (S, E)
    step, element = np.nonzero(touched)
    volume = volume.copy()
    at = cells[element] + x.shape[1] * step[:, None]  # rows of the shapes' nodes stacked
    volume[step, element] = signed_volume(x.reshape(-1, 3), at)
    return volume


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


def _sum_at(index: NDArray, values: NDArray, size: int) -> NDArray[np.float64]:
    """Sums of the vectors ``values`` (K, 3) at the rows ``index`` (K,) of a (size, 3) array."""
    return np.stack([np.bincount(index, values[:, i], minlength=size) for i in range(3)], axis=1)


def _element_sweep(
    x: NDArray,
    cells: NDArray,
    bad: NDArray,
    deficit: NDArray,
    size: NDArray,
    free: NDArray,
    contact: NDArray | None = None,
    plates: NDArray | None = None,
) -> NDArray[np.float64]:
    """One Jacobi pass over the elements ``bad`` (S, E) bool of the shapes ``x`` (S, N, 3):
    each asks ``deficit`` (B,) mm^3 more volume of its vertices (B: the pairs of
    ``np.nonzero(bad)``, in its order), along the directions they may move in (``free``:
    `free_projectors`), at most its ``size`` (B,) mm per vertex (a nearly flat element's
    linearised request can be unbounded); a node takes the mean of its requests. A vertex on a
    plate (``contact`` (S, 2, N) of `Constraints.measure`, with the shapes' ``plates``) is not
    asked to move into it: the gradient's component into the plate is dropped, so the other
    vertices make the volume."""
    shapes, n = x.shape[:2]
    step, element = np.nonzero(bad)
    nodes = cells[element]  # (B, 4)
    at = nodes + n * step[:, None]  # (B, 4): rows of the shapes' nodes stacked, (S * N, 3)
    flat = x.reshape(-1, 3)
    g = np.einsum("eaij,eaj->eai", free[nodes], volume_gradients(flat, at))  # (B, 4, 3)
    for k in range(0 if contact is None else contact.shape[1]):
        on = contact[:, k].reshape(-1)[at]  # (B, 4)
        normal = on[:, :, None] * plates[step, k, NORMAL][:, None, :]  # (B, 4, 3), 0 off it
        into = np.minimum(np.einsum("eaj,eaj->ea", g, normal), 0.0)
        g -= into[:, :, None] * normal
    norm2 = np.einsum("eaj,eaj->e", g, g)
    request = (deficit / np.maximum(norm2, 1e-30))[:, None, None] * g
    length = np.linalg.norm(request, axis=2, keepdims=True)  # (B, 4, 1)
    request *= np.minimum(1.0, size[:, None, None] / np.maximum(length, 1e-30))
    out = _sum_at(at.ravel(), request.reshape(-1, 3), shapes * n)
    count = np.bincount(at.ravel(), minlength=shapes * n)
    return x + (out / np.maximum(count, 1)[:, None]).reshape(x.shape)


def _smoothing_step(x: NDArray, edges: NDArray, nodes: NDArray, free: NDArray) -> NDArray:
    """One Laplacian smoothing step of the nodes ``nodes`` (S, N) bool of the shapes ``x``
    (S, N, 3): each moves to the mean of its mesh neighbours (``edges`` (2, 2M)), along the
    directions it may move in (``free``)."""
    shapes, n = x.shape[:2]
    source, target = edges
    step, edge = np.nonzero(nodes[:, target])  # the edges into a smoothed node
    at = n * step + target[edge]
    flat = x.reshape(-1, 3)
    total = _sum_at(at, flat[n * step + source[edge]], shapes * n)
    count = np.bincount(at, minlength=shapes * n)
    moved = np.flatnonzero(nodes)  # rows of the stacked (S * N, 3)
    out = flat.copy()
    mean = total[moved] / count[moved, None]
    out[moved] += np.einsum("nij,nj->ni", free[moved % n], mean - flat[moved])
    return out.reshape(x.shape)


def _whole_volume_step(
    x: NDArray, cells: NDArray, deficit: NDArray, size: float, free: NDArray
) -> NDArray[np.float64]:
    """The minimum-norm linearised step of each shape ``x`` (S, N, 3) that adds its
    ``deficit`` (S,) mm^3 to its whole volume: the nodes along the sum of their elements'
    volume gradients (interior nodes' cancel), in the directions they may move in, at most
    ``size`` mm per node."""
    shapes, n = x.shape[:2]
    at = (cells.ravel() + n * np.arange(shapes)[:, None]).ravel()  # (S * 4E,)
    g = _sum_at(at, volume_gradients(x, cells).reshape(-1, 3), shapes * n).reshape(x.shape)
    g = np.einsum("nij,snj->sni", free, g)
    step = (deficit / np.maximum(np.einsum("snj,snj->s", g, g), 1e-30))[:, None, None] * g
    longest = np.linalg.norm(step, axis=2).max(axis=1, initial=0.0)  # (S,)
    return x + step * np.minimum(1.0, size / np.maximum(longest, 1e-30))[:, None, None]


def _plate_step(x: NDArray, skin: NDArray, plates: NDArray) -> NDArray:
    """Skin nodes of the shapes ``x`` (S, N, 3) inside a plate (``plates`` (S, 2, 3, 3))
    covering them moved out of it the shorter way: onto its surface along its normal, or, when
    its chest-side edge face is nearer, behind that face along its axis (`EDGE_CLEARANCE` past
    it, so that the plate no longer covers them). Always onto the surface dragged the tissue that
    bulges out behind the plate's edge onto the plate, by up to centimetres: on the graph
    model's compression fold 0, 132 of the 458 skin nodes deeper than 0.5 mm at the last step
    were nearer the edge face, and the projection raised the last step's mean RMSE from 0.619
    to 0.684 mm; leaving by the nearer face it lowers it to 0.602 mm."""
    x = x.copy()
    for k in range(plates.shape[1]):
        along, depth = plate_coordinates(x[:, skin], plates[:, k : k + 1])  # (S, 1, K) each
        along, depth = along[:, 0], depth[:, 0]
        inside = (along >= 0) & (depth > 0)
        behind = inside & (along < depth)
        onto = np.where(inside & ~behind, depth, 0.0)
        back = np.where(behind, along + EDGE_CLEARANCE, 0.0)
        x[:, skin] += onto[..., None] * plates[:, k, None, NORMAL]
        x[:, skin] -= back[..., None] * plates[:, k, None, AXIS]
    return x
