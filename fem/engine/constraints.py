"""Held directions of nodes, node frames, and the model seen in those frames.

A boundary condition of this engine holds a node's displacement along some unit directions
(``u_i . d = 0``: the chest-wall normal, a coordinate axis of a user's constraint file, all
three for a tied node), and a plate bounds a node along the plate normal. The solver
(`fem.engine.solver`) holds and bounds *coordinates*. Each node therefore gets an orthonormal
frame ``R_i`` (columns: the held directions first, then the plate normal's part orthogonal to
them, then the rest), and the solver works on the local coordinates ``y_i = R_i^T x_i``:

    Pi(y) = Pi(x(y)),   g_y = T^T g_x,   K_y = T^T K_x T,   T = blockdiag(R_i),

where the held coordinates are fixed DOFs and a plate's half-space ``n . (x_i - o) >= 0`` is a
bound on one coordinate (the other free coordinates of the node are orthogonal to ``n``; the
held ones do not move). Nodes whose held directions are coordinate axes and whose plates are
normal to an axis keep the identity frame, so a cranio-caudal problem is solved in the
patient frame itself. A held node stays on its tangent plane (small sliding, like ABAQUS'
small-sliding contact).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from fem.engine.assembly import Model, SplitTangent, same_pattern
from fem.engine.contact import RigidPlate
from fem.engine.solver import NewtonSettings, load_ramp

#: Rank tolerance of held directions, and how far a plate normal may lean into the free
#: coordinates it does not bound.
RANK_TOLERANCE = 1e-9

#: The plate gap, mm, within which a node counts as touching (steps land on a plate only to
#: round-off).
ON_PLATE = 1e-9


@dataclass(frozen=True)
class HeldDirections:
    """Directions along which nodes do not move: one row per (node, direction).

    Parameters
    ----------
    nodes : (M,) int
        Node of each row (a node may repeat, once per held direction).
    directions : (M, 3) float
        Unit direction held at that node.
    """

    nodes: NDArray[np.int64]
    directions: NDArray[np.float64]

    @classmethod
    def axes(cls, nodes: NDArray, axes: Sequence[int] = (0, 1, 2)) -> HeldDirections:
        """``nodes`` held along the coordinate ``axes`` (all three: tied)."""
        nodes = np.asarray(nodes, np.int64)
        eye = np.eye(3)[list(axes)]
        return cls(np.repeat(nodes, len(axes)), np.tile(eye, (len(nodes), 1)))

    @classmethod
    def none(cls) -> HeldDirections:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)))

    def __add__(self, other: HeldDirections) -> HeldDirections:
        return HeldDirections(
            np.concatenate([self.nodes, other.nodes]),
            np.concatenate([self.directions, other.directions]),
        )


def _orthonormal_rows(vectors: NDArray) -> NDArray[np.float64]:
    """An orthonormal basis (k <= 3, 3) of the span of ``vectors`` (rows): Gram-Schmidt with
    each vector orthogonalised twice (one pass leaves rounding errors of about 1e-8 when a
    vector is close to the span before it, which let a fourth row through: a direction
    6e-8 off the xy plane, then the coordinate axes), stopping at three rows."""
    basis: list[NDArray] = []
    for v in vectors:
        if len(basis) == 3:
            break
        w = np.asarray(v, np.float64)
        for _ in range(2):
            w = w - sum((w @ e) * e for e in basis)
        if np.linalg.norm(w) > RANK_TOLERANCE:
            basis.append(w / np.linalg.norm(w))
    return np.array(basis).reshape(-1, 3)


def _completed(basis: NDArray, normal: NDArray | None) -> NDArray[np.float64]:
    """A rotation (3, 3) whose columns are ``basis`` (k, 3), then the part of ``normal``
    orthogonal to it (when there is one), then the rest of a right-handed frame."""
    extra = [] if normal is None else [normal]
    full = _orthonormal_rows(np.array([*basis, *extra, *np.eye(3)]))
    if np.linalg.det(full) < 0:
        full[-1] *= -1
    return full.T


def _axis_index(v: NDArray) -> int | None:
    """The coordinate axis a unit vector lies along, or None."""
    k = int(np.argmax(np.abs(v)))
    return k if abs(abs(v[k]) - 1.0) <= RANK_TOLERANCE else None


@dataclass(frozen=True)
class NodeFrames:
    """Local frames of all nodes and which local coordinates are held.

    Attributes
    ----------
    rotations : (N, 3, 3) float
        ``R_i``: columns are node i's local axes in the patient frame (identity for most).
    held : (N, 3) bool
        Held local coordinates.
    rotated : (R,) int
        Nodes whose frame is not the identity.
    """

    rotations: NDArray[np.float64]
    held: NDArray[np.bool_]
    rotated: NDArray[np.int64]

    @classmethod
    def build(
        cls,
        n_nodes: int,
        held: HeldDirections,
        plate_normal: NDArray | None = None,
        plate_nodes: NDArray | None = None,
        edge_normal: NDArray | None = None,
        behind: NDArray | None = None,
    ) -> NodeFrames:
        """Frames in which the ``held`` directions and the plates' ``plate_normal`` are
        coordinates (for the plates' candidate nodes ``plate_nodes``; for those of them
        ``behind`` the plates' chest-side edge, the normal of its face, ``edge_normal``).

        A node keeps the identity frame when its held directions are coordinate axes and the
        plate normal is one too; otherwise its frame is the held directions, then the bounded
        direction's part orthogonal to them, then the rest (right-handed).
        """
        rotations = np.tile(np.eye(3), (n_nodes, 1, 1))
        is_held = np.zeros((n_nodes, 3), bool)
        normal = None if plate_normal is None else np.asarray(plate_normal, float)
        turned = normal is not None and _axis_index(normal) is None
        on_plate, is_behind = np.zeros(n_nodes, bool), np.zeros(n_nodes, bool)
        if normal is not None:
            on_plate[np.asarray(plate_nodes, np.int64)] = True
        if behind is not None:
            is_behind[np.asarray(behind, np.int64)] = True
        rotated = []
        order = np.argsort(held.nodes, kind="stable")
        nodes, starts = np.unique(held.nodes[order], return_index=True)
        for i, dirs in zip(nodes, np.split(held.directions[order], starts[1:]), strict=False):
            axes = [_axis_index(d) for d in dirs]
            if None not in axes and not (on_plate[i] and turned):
                is_held[i, axes] = True
                continue
            basis = _orthonormal_rows(dirs)
            bounded = (edge_normal if is_behind[i] else normal) if on_plate[i] else None
            rotations[i] = _completed(basis, bounded)
            is_held[i, : len(basis)] = True
            rotated.append(i)
        if turned:  # the free candidate nodes turn to the plates
            free = np.setdiff1d(np.flatnonzero(on_plate), nodes)
            rotations[free] = _completed(np.zeros((0, 3)), normal)
            rotated.extend(free)
        return cls(rotations, is_held, np.sort(np.asarray(rotated, np.int64)))

    def to_local(self, x: NDArray) -> NDArray[np.float64]:
        """``y_i = R_i^T x_i`` of positions or vectors (N, 3) or (3N,), same shape back."""
        y = np.array(x, float).reshape(-1, 3)
        r = self.rotated
        y[r] = np.einsum("nji,nj->ni", self.rotations[r], y[r])
        return y.reshape(np.shape(x))

    def to_global(self, y: NDArray) -> NDArray[np.float64]:
        """``x_i = R_i y_i`` of (..., N, 3) positions."""
        x = np.array(y, float)
        r = self.rotated
        x[..., r, :] = np.einsum("nij,...nj->...ni", self.rotations[r], x[..., r, :])
        return x

    def transform(self) -> sparse.csr_matrix:
        """``T = blockdiag(R_i)`` (3N, 3N)."""
        n = len(self.rotations)
        rows = 3 * np.arange(n)[:, None, None] + np.arange(3)[None, :, None]
        cols = 3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]
        rows, cols = np.broadcast_arrays(rows, cols)
        return sparse.csr_matrix(
            (self.rotations.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n)
        )

    def rotate(self, K: sparse.csr_matrix, plan: RotationPlan) -> sparse.csr_matrix:
        """``T^T K T`` (``T = blockdiag(R_i)``) of a CSR matrix with ``plan``'s pattern: only
        the entries in the rows and columns of the rotated nodes change (15x faster than the
        two sparse products with `transform`, equal to round-off)."""
        data = K.data.copy()
        R = self.rotations
        data[plan.rows] = np.einsum("sji,js->is", R[plan.row_nodes], data[plan.rows])  # R_I^T K
        data[plan.cols] = np.einsum("mj,mjk->mk", data[plan.cols], R[plan.col_nodes])  # K R_J
        return sparse.csr_matrix((data, K.indices, K.indptr), shape=K.shape)

    def rotation_plan(self, K: sparse.csr_matrix, rows: bool = True) -> RotationPlan:
        """Where `rotate` reads and writes in ``K.data`` (sorted CSR whose pattern is made of
        full 3 x 3 node blocks, as `fem.engine.assembly.Model.tangent` makes them); with
        ``rows=False`` the columns only (``K T``; of a matrix whose rows hold full node
        triples of columns, as the nodal-averaging factor)."""
        indptr, length, r = K.indptr, np.diff(K.indptr), self.rotated
        first = np.flatnonzero(K.indices % 3 == 0)
        if (
            rows
            and (
                np.any(length % 3)
                or np.any(length[0::3] != length[1::3])
                or np.any(length[0::3] != length[2::3])
            )
        ) or np.any(
            np.diff(K.indices[np.minimum(first[:, None] + np.arange(3), K.nnz - 1)], axis=1) != 1
        ):
            raise ValueError("the tangent's pattern is not made of full 3 x 3 node blocks")
        is_rotated = np.zeros(len(self.rotations), bool)
        is_rotated[r] = True
        r = r if rows else r[:0]
        starts = indptr[3 * r[:, None] + np.arange(3)]  # (R, 3)
        owner = np.repeat(np.arange(len(r)), length[3 * r])
        offsets = np.arange(len(owner)) - np.repeat(
            np.cumsum(length[3 * r]) - length[3 * r], length[3 * r]
        )
        first = first[is_rotated[K.indices[first] // 3]]
        return RotationPlan(
            K.indptr.copy(),
            K.indices.copy(),
            starts[owner].T + offsets,
            r[owner],
            first[:, None] + np.arange(3),
            K.indices[first] // 3,
        )


@dataclass(frozen=True)
class RotationPlan:
    """Gather indices of `NodeFrames.rotate` for one CSR pattern (``indptr``, ``indices``).

    Attributes
    ----------
    rows : (3, S) int
        The three rows of each rotated node, column by column; ``row_nodes`` (S,) its node.
    cols : (M, 3) int
        Each entry triple ``(3J, 3J+1, 3J+2)`` of a rotated node ``J`` in any row;
        ``col_nodes`` (M,) that node.
    """

    indptr: NDArray[np.int32]
    indices: NDArray[np.int32]
    rows: NDArray[np.int64]
    row_nodes: NDArray[np.int64]
    cols: NDArray[np.int64]
    col_nodes: NDArray[np.int64]

    def fits(self, K: sparse.csr_matrix) -> bool:
        """Whether ``K`` has this pattern."""
        return same_pattern((self.indptr, self.indices), K)


class FramedModel:
    """A `Model` seen in node frames: the solver's body, with plates as coordinate bounds.

    Positions are local coordinates ``y`` (N, 3); forces and tangents are transformed with
    ``T`` (see the module docstring). Each plate's candidate node is bounded along its
    ``bounded`` coordinate ``a_i`` with ``c_i = n . R_i e_a``, so ``n . x_i = c_i y_ia +
    (held part)``; its multiplier is ``g_ia / c_i``.

    Raises
    ------
    ValueError
        A plate's normal leans into a free coordinate of a node it does not bound (the node's
        frame was built for another normal).
    """

    def __init__(self, model: Model, frames: NodeFrames) -> None:
        self.model, self.frames = model, frames
        self.body = model.body
        self._plan: RotationPlan | None = None
        self._factor_plan: RotationPlan | None = None
        self.cells = model.cells
        self.plates = [p for p in model.parts if isinstance(p, RigidPlate)]
        self._bounded, self._edges = [], []
        for p in self.plates:
            front = np.ones(len(p.nodes), bool) if p.front is None else p.front
            self._bounded.append(self._coordinate(p.nodes, p.normal, front))
            self._edges.append(self._coordinate(p.nodes, p.axis, ~front))

    def _coordinate(
        self, nodes: NDArray, direction: NDArray, required: NDArray
    ) -> tuple[NDArray, NDArray, NDArray]:
        """For each node: whether ``direction`` is a free coordinate of its frame (up to held
        parts), which one (``a``) and ``c = direction . R e_a``; it must be for the
        ``required`` nodes."""
        R = self.frames.rotations[nodes]  # (M, 3, 3)
        c = np.where(~self.frames.held[nodes], np.einsum("nia,i->na", R, direction), 0.0)
        a = np.argmax(np.abs(c), axis=1)
        coefficient = c[np.arange(len(a)), a]
        leaning = np.abs(c).sum(axis=1) - np.abs(coefficient) > RANK_TOLERANCE
        if (leaning & required).any():
            raise ValueError(
                f"plate direction {direction} is not a coordinate of the frames of "
                f"{int((leaning & required).sum())} of its nodes (plates must be parallel)"
            )
        return (np.abs(coefficient) > RANK_TOLERANCE) & ~leaning, a, coefficient

    def _x(self, y: NDArray) -> NDArray[np.float64]:
        return self.frames.to_global(y)

    def min_jacobian(self, y: NDArray) -> float:
        return self.model.min_jacobian(self._x(y))

    def energy(self, y: NDArray) -> float:
        return self.model.energy(self._x(y))

    def internal_force(self, y: NDArray) -> NDArray[np.float64]:
        return self.frames.to_local(self.model.internal_force(self._x(y)))

    def tangent(self, y: NDArray) -> SplitTangent:
        """``T^T K T`` of the model's tangent, both of its terms."""
        K = self.model.tangent(self._x(y))
        if not self.frames.rotated.size:
            return K
        local, factor = K.local.tocsr(), K.factor.tocsr()
        local.sort_indices()
        factor.sort_indices()
        if self._plan is None or not self._plan.fits(local):
            self._plan = self.frames.rotation_plan(local)
        if self._factor_plan is None or not self._factor_plan.fits(factor):
            self._factor_plan = self.frames.rotation_plan(factor, rows=False)
        return SplitTangent(
            self.frames.rotate(local, self._plan), self.frames.rotate(factor, self._factor_plan)
        )

    def bounds(self, y: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper bounds (3N,) of the local coordinates at ``y`` (+-inf: unbounded):
        each plate's surface for the nodes it covers, and the plane of its chest-side edge
        face for the others once the plate is `RigidPlate.start`-ed (they stay behind it)."""
        x = self._x(y)
        lower = np.full(y.size, -np.inf)
        upper = np.full(y.size, np.inf)
        for plate, surface, edge in zip(self.plates, self._bounded, self._edges, strict=True):
            behind = np.zeros(len(plate.nodes), bool) if plate.front is None else ~plate.front
            for take, (movable, a, c), direction, sign in (
                (plate.covered(x), surface, plate.normal, 1.0),
                (behind, edge, plate.axis, -1.0),
            ):
                take = take & movable
                nodes, a_t, c_t = plate.nodes[take], a[take], sign * c[take]
                # sign * direction . (x - origin) = c y_a + rest >= 0, rest from held parts
                rest = sign * (x[nodes] - plate.origin) @ direction - c_t * y[nodes, a_t]
                bound, dofs, up = -rest / c_t, 3 * nodes + a_t, c_t < 0
                lower[dofs[~up]] = np.maximum(lower[dofs[~up]], bound[~up])
                upper[dofs[up]] = np.minimum(upper[dofs[up]], bound[up])
        return lower, upper

    def contact_forces(self, y: NDArray, gradient: NDArray) -> list[NDArray[np.float64]]:
        """Normal force of each plate's candidate nodes, Pa mm^2 (list of (M,)): the
        multipliers of their bounds, from ``gradient = dPi/dy`` (3N,) at equilibrium."""
        x, g = self._x(y), gradient.reshape(-1, 3)
        out = []
        for plate, (movable, a, c) in zip(self.plates, self._bounded, strict=True):
            touching = plate.covered(x) & movable & (plate.gap(x) <= ON_PLATE)
            multiplier = g[plate.nodes, a] / np.where(movable, c, 1.0)
            out.append(np.where(touching, np.maximum(multiplier, 0.0), 0.0))
        return out

    def update_friction(self, y: NDArray, gradient: NDArray) -> float:
        """Give the plates with friction the normal forces of the equilibrium ``y`` (slip still
        measured from the last converged step): one fixed-point update of the implicit
        normal force. Returns the largest change over the largest force (0: none)."""
        change, scale = 0.0, 0.0
        for plate, force in zip(self.plates, self.contact_forces(y, gradient), strict=True):
            if plate.friction > 0:
                change = max(change, float(np.abs(force - plate.normal_force).max(initial=0.0)))
                scale = max(scale, float(force.max(initial=0.0)))
                plate.normal_force = force
        return change / scale if scale > 0 else 0.0

    def accept(self, y: NDArray, gradient: NDArray, increment: float = 0.0) -> None:
        """Tell the plates that ``y`` is a converged load step, reached by a load
        ``increment`` (friction's slip anchors and normal-force rates)."""
        x = self._x(y)
        for plate, force in zip(self.plates, self.contact_forces(y, gradient), strict=True):
            plate.accept(x, force, increment)

    def predict(self, increment: float) -> None:
        """Extrapolate the plates' normal forces ``increment`` past the last accepted step
        (`fem.engine.contact.RigidPlate.predict`)."""
        for plate in self.plates:
            plate.predict(increment)

    def reject(self) -> None:
        """A load step failed: back to the normal forces of the last converged one."""
        for plate in self.plates:
            plate.normal_force = plate.accepted_force.copy()


def equilibrium_path(
    model: Model,
    frames: NodeFrames,
    x0: NDArray,
    load: Callable[[float], NDArray],
    record: Sequence[float],
    settings: NewtonSettings,
    configure: Callable[[float], None] | None = None,
    max_cutbacks: int = 10,
    prescribed: Callable[[float], NDArray] | None = None,
) -> NDArray[np.float64]:
    """Positions (len(record), N, 3) along a load ramp (`fem.engine.solver.load_ramp`) with the
    held coordinates of ``frames`` fixed at their values in ``x0`` (N, 3) and the plates of
    ``model`` as bounds; ``load`` maps the load factor to the external force (3N,);
    ``prescribed`` maps it to positions (N, 3) whose held coordinates are imposed instead."""
    framed = FramedModel(model, frames)
    Y = load_ramp(
        framed,
        frames.to_local(x0),
        ~frames.held.ravel(),
        lambda s: frames.to_local(load(s)),
        record,
        settings,
        max_cutbacks=max_cutbacks,
        configure=configure,
        prescribed=None if prescribed is None else lambda s: frames.to_local(prescribed(s)),
    )
    return frames.to_global(Y)
