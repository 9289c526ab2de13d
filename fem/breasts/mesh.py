"""Labelled volume -> linear tetrahedral breast mesh.

The mesher is a body-centred-cubic (BCC) lattice fitted to the segmented domain, in the spirit
of isosurface stuffing (Labelle & Shewchuk 2007), written with NumPy/SciPy only:

1. ``signed_distance``: signed distance ``phi`` (mm) to the boundary of the tissue domain
   (fat, gland and muscle), negative inside;
2. ``bcc_lattice``: a lattice of congruent tetrahedra (dihedral angles 60 and 90 degrees) with
   spacing ``h`` chosen so that about ``target_elements`` of them cover the domain; the
   tetrahedra whose centroid lies inside are kept (largest face-connected component);
3. ``snap_to_surface``: boundary nodes move onto ``phi = 0`` along ``grad phi``; a move that
   would push an element below the quality floor is halved, then refused;
4. the level set is offset by the volume that flat boundary triangles cut off convex parts
   of the surface, and snapping repeated; interior nodes are smoothed where that improves
   their worst element;
5. ``h`` is re-solved until the element count lies in the requested window.

Element tissue is the majority label of the voxels inside (64 fixed sample points per
element); ``annotate`` then derives the node tissue codes, flags and skin triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import skfem
from numpy.typing import NDArray
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from fem.breasts.phantom import LabelVolume
from fem.contract.quality import (
    boundary_faces,
    check_cells,
    posterior_cut,
    quality_report,
    radius_ratio,
    signed_volume,
)
from fem.contract.trajectory import TISSUE_BIT, NodeFlag, Tissue, Trajectory

#: Fixed barycentric sample points (64 per element, uniform in the tetrahedron).
_SAMPLES = np.random.default_rng(20261123).dirichlet(np.ones(4), size=64)


def signed_distance(mask: NDArray[np.bool_], spacing: NDArray) -> NDArray[np.float32]:
    """Signed distance (mm) to the boundary between ``mask`` and its complement.

    Negative inside. Voxel centres adjacent to the boundary get -/+ half a voxel, so the zero
    level set passes through the voxel faces and encloses the voxelised volume.

    Parameters
    ----------
    mask : (I, J, K) bool
        Domain voxels.
    spacing : (3,) float
        Voxel edge lengths, mm.
    """
    outside = ndimage.distance_transform_edt(~mask, sampling=spacing)
    inside = ndimage.distance_transform_edt(mask, sampling=spacing)
    half = 0.5 * float(np.min(spacing))
    return np.where(mask, half - inside, outside - half).astype(np.float32)


def coarse_signed_distance(
    mask: NDArray[np.bool_], affine: NDArray, max_voxel: float
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """`signed_distance` on the mask block-averaged by the largest integer factor that keeps
    voxels at most ``max_voxel`` mm wide.

    Returns
    -------
    phi : (I', J', K') float32
        Signed distance, mm.
    affine : (4, 4) float64
        Voxel index -> world mm of the (possibly coarsened) grid.
    """
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    f = max(1, int(max_voxel // spacing.max()))
    if f == 1:
        return signed_distance(mask, spacing), affine
    pad = [(0, (-n) % f) for n in mask.shape]
    m = np.pad(mask, pad).astype(np.float32)
    shape = [n // f for n in m.shape]
    blocks = m.reshape(shape[0], f, shape[1], f, shape[2], f).mean(axis=(1, 3, 5)) > 0.5
    coarse = affine.copy()
    coarse[:3, :3] *= f
    coarse[:3, 3] += affine[:3, :3] @ np.full(3, (f - 1) / 2)
    return signed_distance(blocks, spacing * f), coarse


def bcc_lattice(
    lo: NDArray, hi: NDArray, h: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Body-centred-cubic tetrahedral lattice covering the box ``[lo, hi]``.

    Nodes are the cube corners and cube centres of a grid of spacing ``h``; every pair of
    face-adjacent centres spans four tetrahedra with the four edges of their shared face
    (12 tetrahedra per ``h^3``, all congruent).

    Returns
    -------
    points : (N, 3) float64
    cells : (E, 4) int64, positively oriented
    """
    n = np.maximum(np.ceil((np.asarray(hi) - np.asarray(lo)) / h).astype(int), 1)
    corner_shape, centre_shape = tuple(n + 1), tuple(n)
    ci = np.indices(corner_shape).reshape(3, -1).T
    mi = np.indices(centre_shape).reshape(3, -1).T
    points = np.vstack([lo + h * ci, lo + h * (mi + 0.5)])
    n_corner = len(ci)

    def corner(idx: NDArray) -> NDArray:
        return np.ravel_multi_index(idx.T, corner_shape)

    def centre(idx: NDArray) -> NDArray:
        return n_corner + np.ravel_multi_index(idx.T, centre_shape)

    cells = []
    for axis in range(3):
        a1, a2 = [ax for ax in range(3) if ax != axis]
        m = mi[mi[:, axis] < n[axis] - 1]  # centres with a neighbour along +axis
        e = np.eye(3, dtype=int)
        m2 = m + e[axis]
        face = m + e[axis]  # corner index of the shared face's origin
        square = [face, face + e[a1], face + e[a1] + e[a2], face + e[a2]]
        for s in range(4):
            cells.append(
                np.column_stack(
                    [centre(m), centre(m2), corner(square[s]), corner(square[(s + 1) % 4])]
                )
            )
    cells = np.vstack(cells)
    neg = signed_volume(points, cells) < 0
    cells[neg] = cells[neg][:, [0, 1, 3, 2]]
    return points, cells


def _node_cell_matrix(n_nodes: int, cells: NDArray) -> sparse.csr_matrix:
    """(N, E) incidence matrix, 1 where a node belongs to an element."""
    e = np.repeat(np.arange(len(cells)), 4)
    return sparse.csr_matrix(
        (np.ones(e.size, np.int8), (cells.ravel(), e)), shape=(n_nodes, len(cells))
    )


def _largest_component(cells: NDArray) -> NDArray[np.int64]:
    """Cells of the largest face-connected component."""
    faces = np.sort(cells[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, inv = np.unique(faces, axis=0, return_inverse=True)
    inv = inv.ravel()
    owner = np.repeat(np.arange(len(cells)), 4)
    order = np.argsort(inv, kind="stable")
    same = inv[order][1:] == inv[order][:-1]
    a, b = owner[order][:-1][same], owner[order][1:][same]
    adj = sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(len(cells),) * 2)
    _, comp = csgraph.connected_components(adj, directed=False)
    return cells[comp == np.bincount(comp).argmax()]


def compact_mesh(points: NDArray, cells: NDArray) -> tuple[NDArray, NDArray]:
    """Drop the nodes no cell uses and renumber the cells, keeping node order."""
    used, inv = np.unique(cells, return_inverse=True)
    return points[used], inv.reshape(cells.shape).astype(np.int64)


def crop_with_margin(volume: LabelVolume, margin: int = 2) -> LabelVolume:
    """The labelled voxels of ``volume`` with ``margin`` voxels of background around them.

    Where the tissue reaches the edge of the image (a segmentation cropped at the chest
    wall), the margin is added as background, so the tissue ends at the image's edge instead
    of continuing beyond it. The affine keeps voxel -> world positions of the original.
    """
    idx = np.argwhere(volume.labels != Tissue.BACKGROUND)
    lo, hi = idx.min(0) - margin, idx.max(0) + margin + 1
    shape = np.array(volume.labels.shape)
    inside = tuple(
        slice(a, b) for a, b in zip(np.maximum(lo, 0), np.minimum(hi, shape), strict=True)
    )
    outside = [(int(max(0, -a)), int(max(0, b - n))) for a, b, n in zip(lo, hi, shape, strict=True)]
    affine = volume.affine.copy()
    affine[:3, 3] += affine[:3, :3] @ lo
    return LabelVolume(np.pad(volume.labels[inside], outside), affine, volume.source)


class _Field:
    """Trilinear interpolation of a voxel field at world points (mm)."""

    def __init__(self, values: NDArray, affine: NDArray) -> None:
        self.values = values
        inv = np.linalg.inv(affine)
        self.rot, self.shift = inv[:3, :3], inv[:3, 3]
        self.step = 0.5 * float(np.min(np.linalg.norm(affine[:3, :3], axis=0)))

    def __call__(self, x: NDArray) -> NDArray[np.float64]:
        ijk = x @ self.rot.T + self.shift
        return ndimage.map_coordinates(self.values, ijk.T, order=1, mode="nearest").astype(
            np.float64
        )

    def gradient(self, x: NDArray) -> NDArray[np.float64]:
        e = self.step * np.eye(3)
        return np.stack(
            [(self(x + e[k]) - self(x - e[k])) / (2 * self.step) for k in range(3)], axis=1
        )


def snap_to_surface(
    points: NDArray,
    cells: NDArray,
    nodes: NDArray,
    phi: _Field,
    iterations: int,
    min_quality: float,
    max_step: float,
    level: float = 0.0,
) -> NDArray[np.float64]:
    """Move ``nodes`` onto the level set ``phi = level`` without breaking element quality.

    Each iteration proposes a Newton step ``-phi grad(phi) / |grad(phi)|^2`` (capped at
    ``max_step``); steps that drive an incident element's radius ratio below ``min_quality``
    are halved up to three times, then refused for that iteration.

    Returns
    -------
    (N, 3) float64
        Updated node coordinates.
    """
    x = points.copy()
    incidence = _node_cell_matrix(len(points), cells)
    touched = np.flatnonzero(incidence[nodes].sum(axis=0).A1)
    sub = cells[touched]
    for _ in range(iterations):
        g = phi.gradient(x[nodes])
        step = (
            -(phi(x[nodes]) - level)[:, None] * g / np.maximum((g * g).sum(1, keepdims=True), 1e-6)
        )
        length = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, max_step / np.maximum(length, 1e-12))
        alpha = np.ones(len(nodes))
        for trial in range(5):
            trial_x = x.copy()
            trial_x[nodes] += alpha[:, None] * step
            bad = radius_ratio(trial_x, sub) < min_quality
            if not bad.any():
                break
            bad_nodes = np.isin(nodes, sub[bad])
            alpha[bad_nodes] = 0.0 if trial >= 3 else 0.5 * alpha[bad_nodes]
        else:  # refusing every move of the offending nodes restores the previous valid state
            trial_x = x
        x = trial_x
    return x


def smooth_interior(
    points: NDArray, cells: NDArray, interior: NDArray, iterations: int, floor: float = 0.3
) -> NDArray[np.float64]:
    """Laplacian smoothing of ``interior`` nodes, guarded by element quality.

    A node moves to the centroid of its neighbours only where that raises the radius ratio of
    its worst element; moves that together push a shared element below ``min(old, floor)``
    are undone.
    """
    x = points.copy()
    inc = _node_cell_matrix(len(points), cells)
    adj = (inc @ inc.T).tocsr()
    adj.setdiag(0)
    adj.eliminate_zeros()
    adj.data[:] = 1
    deg = np.asarray(adj.sum(axis=1)).ravel()
    for _ in range(iterations):
        rr = radius_ratio(x, cells)
        trial = x.copy()
        trial[interior] = (adj @ x)[interior] / np.maximum(deg[interior], 1)[:, None]
        better = worst_per_node(cells, radius_ratio(trial, cells), len(x)) > worst_per_node(
            cells, rr, len(x)
        )
        moved = interior[better[interior]]
        new = x.copy()
        new[moved] = trial[moved]
        while True:
            bad = radius_ratio(new, cells) < np.minimum(rr, floor)
            undo = np.intersect1d(cells[bad], moved)
            if undo.size == 0:
                break
            new[undo] = x[undo]
            moved = np.setdiff1d(moved, undo)
        x = new
    return x


def worst_per_node(cells: NDArray, values: NDArray, n_nodes: int) -> NDArray[np.float64]:
    """Minimum of a per-element value over the elements sharing each node, shape (N,)."""
    worst = np.full(n_nodes, np.inf)
    for k in range(cells.shape[1]):
        np.minimum.at(worst, cells[:, k], values)
    return worst


def element_tissue(volume: LabelVolume, points: NDArray, cells: NDArray) -> NDArray[np.uint8]:
    """Majority tissue label of the voxels inside each element (64 sample points each).

    Elements whose samples all fall on background (thin boundary caps) take the majority
    label of their node-neighbour elements.
    """
    x = np.einsum("sk,ekd->esd", _SAMPLES, points[cells]).reshape(-1, 3)
    inv = np.linalg.inv(volume.affine)
    ijk = np.rint(x @ inv[:3, :3].T + inv[:3, 3]).astype(np.int64)
    shape = np.array(volume.labels.shape)
    inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
    lab = np.zeros(len(x), np.uint8)
    lab[inside] = volume.labels[tuple(ijk[inside].T)]
    lab = lab.reshape(len(cells), -1)
    votes = np.stack([(lab == t).sum(1) for t in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)], 1)
    tissue = np.where(
        votes.sum(1) > 0, np.array([Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE])[votes.argmax(1)], 0
    )
    inc = _node_cell_matrix(len(points), cells)
    neighbours = (inc.T @ inc).tocsr()
    while (tissue == 0).any():
        onehot = np.stack(
            [tissue == t for t in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)], 1
        ).astype(float)
        nv = neighbours @ onehot
        fill = (tissue == 0) & (nv.sum(1) > 0)
        if not fill.any():
            raise ValueError(f"{volume.source}: mesh elements do not overlap any tissue voxel")
        tissue[fill] = np.array([Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE])[nv[fill].argmax(1)]
    return tissue.astype(np.uint8)


def annotate(
    points: NDArray,
    cells: NDArray,
    tissue: NDArray,
    metadata: dict | None = None,
    source: str = "mesh",
) -> Trajectory:
    """Build the mesh-only `Trajectory`: node tissue codes, node flags and skin triangles.

    * node code: OR of `TISSUE_BIT` over the elements sharing the node (paper Table 2);
    * skin: boundary triangles of fat/gland elements; ``SKIN`` flags their nodes; a breast
      without muscle elements (a segmentation cropped at the chest wall) has its flat
      posterior cut face (`posterior_cut`) left out: that face is its chest wall;
    * ``MUSCLE_INTERFACE``: nodes shared by muscle and fat/gland elements;
    * ``UPPER_CONTACT`` / ``LOWER_CONTACT``: skin nodes whose area-weighted normal points
      cranially (+z) / caudally (-z), i.e. that can meet the upper / lower plate;
    * ``BOUNDARY``: nodes of any boundary triangle (skin or chest-wall cut).
    """
    points = np.asarray(points, np.float64)
    cells = np.asarray(cells, np.int64)
    tissue = np.asarray(tissue, np.uint8)
    check_cells(points, cells, source)
    n = len(points)
    bits = np.zeros(len(cells), np.uint8)
    for t, bit in TISSUE_BIT.items():
        bits[tissue == t] = bit
    code = np.zeros(n, np.uint8)
    for k in range(4):
        np.bitwise_or.at(code, cells[:, k], bits)
    faces, owner = boundary_faces(points, cells)
    skin = faces[tissue[owner] != Tissue.MUSCLE]
    if not (tissue == Tissue.MUSCLE).any():  # the chest wall is the image's posterior cut
        skin = skin[~posterior_cut(points, skin)]
    flags = np.zeros(n, np.uint8)
    flags[np.unique(faces)] |= np.uint8(NodeFlag.BOUNDARY)
    flags[np.unique(skin)] |= np.uint8(NodeFlag.SKIN)
    muscle, breast = (
        code & TISSUE_BIT[Tissue.MUSCLE],
        code & (TISSUE_BIT[Tissue.FAT] | TISSUE_BIT[Tissue.GLAND]),
    )
    flags[(muscle > 0) & (breast > 0)] |= np.uint8(NodeFlag.MUSCLE_INTERFACE)
    p = points[skin]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    vertex_normal = np.zeros((n, 3))
    for k in range(3):
        np.add.at(vertex_normal, skin[:, k], area_normal)
    skin_nodes = (flags & NodeFlag.SKIN) > 0
    flags[skin_nodes & (vertex_normal[:, 2] > 0)] |= np.uint8(NodeFlag.UPPER_CONTACT)
    flags[skin_nodes & (vertex_normal[:, 2] < 0)] |= np.uint8(NodeFlag.LOWER_CONTACT)
    return Trajectory(
        points=points,
        cells=cells,
        tissue=tissue,
        node_tissue_code=code,
        node_flags=flags,
        skin=skin,
        metadata=dict(metadata or {}),
    )


@dataclass(frozen=True)
class Mesher:
    """Labelled volume -> tetrahedral `Trajectory` with a target element count.

    Parameters
    ----------
    target_elements : int
        Desired number of tetrahedra.
    tolerance : int
        Accepted deviation from ``target_elements``.
    snap_iterations : int
        Iterations of boundary snapping.
    smooth_iterations : int
        Iterations of quality-guarded interior smoothing.
    min_quality : float
        Radius-ratio floor that snapping and smoothing never cross.
    max_attempts : int
        Lattice spacings tried before giving up on the element-count window.
    distance_resolution : float
        The signed distance is computed on voxels at most ``h / distance_resolution`` wide
        (the segmentation is block-averaged by an integer factor when it is finer), which
        keeps the distance transform cheap for large breasts.
    """

    target_elements: int = 2250
    tolerance: int = 250
    snap_iterations: int = 6
    smooth_iterations: int = 2
    min_quality: float = 0.2
    max_attempts: int = 12
    distance_resolution: float = 6.0

    def __post_init__(self) -> None:
        rules = {  # setting: (holds, what it must)
            "target_elements": (self.target_elements >= 1, "be at least 1"),
            "tolerance": (self.tolerance >= 0, "be >= 0"),
            "snap_iterations": (self.snap_iterations >= 0, "be >= 0"),
            "smooth_iterations": (self.smooth_iterations >= 0, "be >= 0"),
            "min_quality": (0 <= self.min_quality < 1, "lie in [0, 1)"),
            "max_attempts": (self.max_attempts >= 1, "be at least 1"),
            "distance_resolution": (self.distance_resolution > 0, "be > 0"),
        }
        for key, (holds, rule) in rules.items():
            if not holds:
                raise ValueError(f"mesher.{key} must {rule}, got {getattr(self, key)!r}")

    def __call__(self, volume: LabelVolume, metadata: dict | None = None) -> Trajectory:
        labels = volume.labels
        if not np.isin(labels, (Tissue.FAT, Tissue.GLAND)).any():
            raise ValueError(f"{volume.source}: no breast labels (fat or gland) in the volume")
        cropped = crop_with_margin(volume, margin=2)
        affine = cropped.affine
        domain = cropped.labels != Tissue.BACKGROUND
        domain_volume = float(domain.sum()) * volume.voxel_volume
        h = (12.0 * domain_volume / self.target_elements) ** (1 / 3)
        phi = _Field(*coarse_signed_distance(domain, affine, h / self.distance_resolution))
        corners = (
            np.array(np.meshgrid(*[[0, s - 1] for s in cropped.labels.shape], indexing="ij"))
            .reshape(3, -1)
            .T
        )
        world = corners @ affine[:3, :3].T + affine[:3, 3]
        lo, hi = world.min(0), world.max(0)
        tried: list[tuple[float, int]] = []
        best: tuple[NDArray, NDArray] | None = None
        for _ in range(self.max_attempts):
            points, cells = self._fit(phi, lo, hi, h, domain_volume)
            tried.append((h, len(cells)))
            miss = abs(len(cells) - self.target_elements)
            if miss <= self.tolerance and (
                best is None or miss < abs(len(best[1]) - self.target_elements)
            ):
                best = (points, cells)
            # Accept a first hit only when it is close; otherwise one secant step refines it.
            if best is not None and (miss <= self.tolerance / 2 or len(tried) >= 3):
                break
            h = self._next_spacing(tried)
        if best is not None:
            points, cells = best
        else:
            raise RuntimeError(
                f"{volume.source}: no lattice spacing gave {self.target_elements} +- {self.tolerance} "
                f"elements (tried {[(round(a, 2), b) for a, b in tried]})"
            )
        tissue = element_tissue(cropped, points, cells)
        faces, _ = boundary_faces(points, cells)
        surface_gap = np.abs(phi(points[np.unique(faces)]))
        mesh_volume = float(signed_volume(points, cells).sum())
        seg_tissue = {
            t.name.lower(): float((labels == t).sum()) * volume.voxel_volume
            for t in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)
        }
        info = {
            "n_nodes": len(points),
            "n_elements": len(cells),
            "lattice_spacing_mm": h,
            "mesh_volume_cm3": mesh_volume / 1e3,
            "segmented_volume_cm3": domain_volume / 1e3,
            "volume_error": mesh_volume / domain_volume - 1.0,
            "segmented_volume_fraction": {k: v / domain_volume for k, v in seg_tissue.items()},
            "element_fraction": {
                t.name.lower(): float((tissue == t).mean())
                for t in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE)
            },
            "surface_distance_mm": {
                "max": float(surface_gap.max()),
                "p95": float(np.percentile(surface_gap, 95)),
            },
            "quality": quality_report(points, cells),
        }
        return annotate(
            points, cells, tissue, {**(metadata or {}), "mesh": info}, source=volume.source
        )

    def _fit(
        self, phi: _Field, lo: NDArray, hi: NDArray, h: float, domain_volume: float
    ) -> tuple[NDArray, NDArray]:
        points, cells = bcc_lattice(lo - h, hi + h, h)
        keep = phi(points[cells].mean(1)) < 0
        if not keep.any():
            return points[:0], cells[:0]
        points, cells = compact_mesh(points, _largest_component(cells[keep]))
        faces, _ = boundary_faces(points, cells)
        surface = np.unique(faces)
        snapped = snap_to_surface(
            points, cells, surface, phi, self.snap_iterations, self.min_quality, 0.5 * h
        )
        # Boundary slivers: elements whose four nodes all lie on the surface and that snapping
        # flattened (caps of a few mm^3).
        on_surface = np.zeros(len(points), bool)
        on_surface[surface] = True
        flat = on_surface[cells].all(1) & (radius_ratio(snapped, cells) < 2 * self.min_quality)
        if flat.any():
            kept = _largest_component(cells[~flat])
            used = np.unique(kept)
            snapped, cells = compact_mesh(snapped, kept)
            surface = np.flatnonzero(on_surface[used])
        # Flat triangles inscribed in a convex surface lose volume (the chord sagitta, about
        # h^2 / 8R): snap once more to the level set offset by the mean missing thickness.
        faces, _ = boundary_faces(snapped, cells)
        p = snapped[faces]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
        level = (domain_volume - signed_volume(snapped, cells).sum()) / area
        points = snap_to_surface(snapped, cells, surface, phi, 3, self.min_quality, 0.5 * h, level)
        faces, _ = boundary_faces(points, cells)
        interior = np.setdiff1d(np.arange(len(points)), np.unique(faces))
        points = smooth_interior(points, cells, interior, self.smooth_iterations)
        return points, cells

    def _next_spacing(self, tried: list[tuple[float, int]]) -> float:
        h, count = tried[-1]
        target = self.target_elements
        guess = h * (max(count, 1) / target) ** (1 / 3)
        # Bracket with the closest tries on either side and stay strictly inside the bracket.
        too_fine = [a for a, c in tried if c > target + self.tolerance]  # h too small
        too_coarse = [a for a, c in tried if c < target - self.tolerance]
        if too_fine and too_coarse:
            a, b = max(too_fine), min(too_coarse)
            if not a < guess < b:
                guess = 0.5 * (a + b)
        return guess


def refine(traj: Trajectory, levels: int = 1) -> tuple[Trajectory, NDArray[np.int64]]:
    """``traj``'s mesh with every tetrahedron split into eight, ``levels`` times (scikit-fem's
    `MeshTet.refined`): the same geometry, tissue boundaries and chest wall, so a comparison
    with the coarse mesh measures discretisation error only.

    The coarse nodes keep their indices (the first ``traj.n_nodes`` nodes of the fine mesh),
    so the fine mesh's positions at them are ``positions[:, :traj.n_nodes]``; each fine
    element inherits the tissue of its parent, and the node flags and skin are rebuilt
    (`annotate`).

    Returns
    -------
    fine : Trajectory
        The refined mesh (8^levels times the elements), with ``traj``'s metadata.
    parent : (E_fine,) int64
        The coarse element each fine element lies in.
    """
    coarse = skfem.MeshTet(traj.points.T.copy(), traj.cells.T.copy())
    fine = coarse.refined(levels)
    points, cells = fine.p.T.copy(), fine.t.T.copy()
    parent = coarse.element_finder()(*points[cells].mean(axis=1).T).astype(np.int64)
    negative = signed_volume(points, cells) < 0
    cells[negative] = cells[negative][:, [0, 2, 1, 3]]
    return annotate(points, cells, traj.tissue[parent], dict(traj.metadata), traj.source), parent
