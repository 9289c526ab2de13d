"""Is a predicted shape physically possible? Inverted elements, volume change, plate penetration.

A surrogate predicts node positions one node at a time, so nothing stops it from turning a
tetrahedron inside out, losing volume that nearly incompressible tissue cannot lose, or
pushing skin through a compression plate. `ValidityProjection` (the ``projection`` settings
of ``conf/predict.yaml``) first moves every predicted shape onto a valid one
(`fem.contract.projection.project_steps`); `check_shapes` then measures all three on every
shape that ``predict.py`` writes, and `PhysicalChecks` (the ``checks`` settings) decides
whether a violation is a warning or refuses the output.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, replace

import numpy as np
from numpy.typing import NDArray

from fem.contract.plates import NORMAL, ORIGIN
from fem.contract.projection import StepProjections, constraints, plate_depth, project_steps
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Trajectory
from fem.engine.boundary import chest_wall
from mammo_net.predictor import BreastShapes


@dataclass(frozen=True)
class ShapeCheck:
    """What one deformed shape does to the mesh it deforms.

    Attributes
    ----------
    inverted_elements : int
        Tetrahedra whose signed volume is not positive.
    volume_change : float
        ``V / V_reference - 1`` of the whole mesh (the FE's own change is below 1 %).
    nodes_beyond_plates : int
        Skin nodes under a plate that lie inside it by more than the tolerance.
    max_plate_penetration_mm : float
        The deepest of them, mm (0 when none).
    """

    inverted_elements: int
    volume_change: float
    nodes_beyond_plates: int = 0
    max_plate_penetration_mm: float = 0.0


def plate_penetration(points: NDArray, skin: NDArray, plates: NDArray) -> NDArray[np.float64]:
    """How far each skin node lies inside a plate, mm (0 outside both).

    Parameters
    ----------
    points : (N, 3) float
        Node positions, mm.
    skin : (S,) int
        Skin node indices.
    plates : (2, 3, 3) float
        Frames (origin, normal, axis) of the lower and the upper plate
        (`fem.contract.plates`): a plate covers the nodes in front of its chest-side edge.

    Returns
    -------
    (S,) float64
        The deepest `fem.contract.plates.penetration` of each node into a plate covering it,
        0 when it lies in front of both plates or is covered by neither.
    """
    return plate_depth(points, skin, plates).max(axis=0)


def check_shape(
    cells: NDArray,
    reference: NDArray,
    points: NDArray,
    skin: NDArray | None = None,
    plates: NDArray | None = None,
    tolerance_mm: float = 0.5,
) -> ShapeCheck:
    """Measure `ShapeCheck` of the shape ``points`` (N, 3) of a mesh whose stress-free
    shape is ``reference`` (N, 3); plate penetration when ``plates`` (2, 3, 3), the frames of
    the lower and the upper plate, is given."""
    volume = signed_volume(points, cells)
    change = float(volume.sum() / signed_volume(reference, cells).sum() - 1.0)
    if plates is None:
        return ShapeCheck(int((volume <= 0).sum()), change)
    depth = plate_penetration(points, skin, plates)
    beyond = depth > tolerance_mm
    return ShapeCheck(
        int((volume <= 0).sum()), change, int(beyond.sum()), float(depth.max(initial=0.0))
    )


def check_shapes(
    traj: Trajectory, shapes: BreastShapes, tolerance_mm: float = 0.5
) -> dict[str, ShapeCheck]:
    """The checks of every shape ``predict.py`` writes, by output name: ``unloaded`` (against
    the imaged mesh) and ``compressed_<t>mm`` (against the unloaded shape, with its plates)."""
    unloaded = shapes.unloaded[-1].astype(np.float64)
    out = {"unloaded": check_shape(traj.cells, traj.points, unloaded)}
    skin = traj.flagged(NodeFlag.SKIN)
    for k, t in enumerate(shapes.thickness):
        out[f"compressed_{t:g}mm"] = check_shape(
            traj.cells,
            unloaded,
            shapes.compressed[k, -1].astype(np.float64),
            skin,
            shapes.plates[k, -1],
            tolerance_mm,
        )
    return out


class PhysicallyImpossible(ValueError):
    """A predicted shape failed a physical check and the settings refuse it."""


@dataclass(frozen=True)
class PhysicalChecks:
    """What counts as a physically impossible prediction, and what happens to it.

    This is the ``checks`` node of ``conf/predict.yaml``; its keys are these arguments.

    Parameters
    ----------
    max_volume_change : float
        Largest ``|V / V_reference - 1|`` accepted (tissue is nearly incompressible).
    plate_tolerance_mm : float
        Depth inside a plate up to which a skin node counts as on it, mm.
    on_violation : {"warn", "refuse"}
        ``warn``: write the output, warn, and record the checks; ``refuse``: raise
        `PhysicallyImpossible` before anything is written.
    """

    max_volume_change: float = 0.05
    plate_tolerance_mm: float = 0.5
    on_violation: str = "warn"

    def __post_init__(self) -> None:
        if self.on_violation not in ("warn", "refuse"):
            raise ValueError(
                f"checks.on_violation must be 'warn' or 'refuse', got {self.on_violation!r}"
            )
        for key in ("max_volume_change", "plate_tolerance_mm"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"checks.{key} must be >= 0, got {getattr(self, key)!r}")

    def violations(self, checks: dict[str, ShapeCheck]) -> list[str]:
        """One sentence per failed check."""
        out = []
        for name, c in checks.items():
            if c.inverted_elements:
                out.append(f"{name}: {c.inverted_elements} inverted tetrahedra")
            if abs(c.volume_change) > self.max_volume_change:
                out.append(
                    f"{name}: volume changed by {100 * c.volume_change:+.1f} % "
                    f"(checks.max_volume_change: {100 * self.max_volume_change:g} %)"
                )
            if c.nodes_beyond_plates:
                out.append(
                    f"{name}: {c.nodes_beyond_plates} skin nodes inside a plate, up to "
                    f"{c.max_plate_penetration_mm:.1f} mm"
                )
        return out

    def __call__(self, traj: Trajectory, shapes: BreastShapes) -> dict:
        """Check every output shape; warn or refuse as configured. Returns the record to store
        with the output: each shape's `ShapeCheck`, the violations and the settings.

        Raises
        ------
        PhysicallyImpossible
            A check failed and ``on_violation`` is ``refuse``.
        """
        checks = check_shapes(traj, shapes, self.plate_tolerance_mm)
        violations = self.violations(checks)
        if violations and self.on_violation == "refuse":
            raise PhysicallyImpossible(
                f"{traj.source}: the predicted shapes are physically impossible: "
                + "; ".join(violations)
                + " (checks.on_violation=warn writes them anyway)"
            )
        for v in violations:
            warnings.warn(f"{traj.source}: {v}", stacklevel=2)
        return {
            "shapes": {name: asdict(c) for name, c in checks.items()},
            "violations": violations,
            "settings": asdict(self),
        }


@dataclass(frozen=True)
class ValidityProjection:
    """Predicted shapes moved as little as they need to be physically valid, every recorded
    step (`fem.contract.projection.project_steps`): each element's volume at least
    ``min_volume_ratio`` of its reference, no skin node inside a plate covering it, the whole
    volume within ``volume_tolerance`` of its reference, and the chest wall held as the FE
    holds it (the sliding wall: muscle nodes still, interface nodes along the wall; nothing
    when the mesh has no chest wall). References: the imaged mesh for the unloaded-state
    steps, the (projected) unloaded shape for the compression steps.

    This is the ``projection`` node of ``conf/predict.yaml``; its keys are these arguments.
    """

    min_volume_ratio: float = 0.05
    volume_tolerance: float = 0.01

    def __post_init__(self) -> None:
        if not 0 < self.min_volume_ratio < 1:
            raise ValueError(
                f"projection.min_volume_ratio must lie in (0, 1), got {self.min_volume_ratio!r}"
            )
        if not self.volume_tolerance > 0:
            raise ValueError(
                f"projection.volume_tolerance must be > 0, got {self.volume_tolerance!r}"
            )

    def __call__(self, traj: Trajectory, shapes: BreastShapes) -> tuple[BreastShapes, dict]:
        """The projected shapes, and the record to store with them: steps moved, the largest
        RMS and maximum node displacement, mm, the steps no valid shape was found for (kept as
        predicted, with a warning: the checks then report them) and the settings."""
        skin = traj.flagged(NodeFlag.SKIN)
        tolerance = (-self.volume_tolerance, self.volume_tolerance)

        def valid_shapes(reference: NDArray, steps: NDArray, plates=None) -> StepProjections:
            try:  # the wall as the step starting from ``reference`` holds it
                wall = chest_wall(traj, reference)
                held = wall.nodes, wall.directions
            except ValueError:  # no chest wall in this mesh: nothing held
                held = None
            c = constraints(
                traj.cells,
                reference,
                None if plates is None else skin,
                self.min_volume_ratio,
                tolerance,
                held,
            )
            return project_steps(c, steps.reshape(-1, traj.n_nodes, 3), plates)

        unloaded = valid_shapes(traj.points, shapes.unloaded)
        start = unloaded.points[-1] if len(shapes.unloaded) else traj.points
        k, t = shapes.compressed.shape[:2]
        compressed = valid_shapes(start, shapes.compressed, shapes.plates.reshape(k * t, 2, 3, 3))
        failed = [f"unloaded step {i + 1}: {why}" for i, why in unloaded.failed.items()]
        failed += [
            f"compression {shapes.thickness[i // t]:g} mm step {i % t + 1}: {why}"
            for i, why in compressed.failed.items()
        ]
        if failed:
            warnings.warn(
                f"{traj.source}: no valid shape found for {len(failed)} step(s), written as "
                f"predicted; first: {failed[0]}",
                stacklevel=2,
            )
        projected = {}
        for name, p, predicted in (
            ("unloaded", unloaded, shapes.unloaded),
            ("compressed", compressed, shapes.compressed),
        ):
            points = p.points.copy()
            for i in p.failed:  # kept as predicted
                points[i] = predicted.reshape(-1, traj.n_nodes, 3)[i]
            projected[name] = points.reshape(predicted.shape).astype(np.float32)
        moved = [unloaded, compressed]
        record = {
            "steps_moved": int(sum((p.sweeps > 0).sum() for p in moved)),
            "moved_rms_mm": float(max(p.moved_rms_mm.max(initial=0.0) for p in moved)),
            "moved_max_mm": float(max(p.moved_max_mm.max(initial=0.0) for p in moved)),
            "failed_steps": failed,
            "settings": asdict(self),
        }
        return replace(shapes, **projected), record

    def project_step(self, traj: Trajectory, step: str, predicted: NDArray) -> NDArray[np.float32]:
        """One step's predicted shapes ``predicted`` (T, N, 3) of ``traj`` projected, the other
        step's shapes from the FE (`step_shapes`): the models of one step judged alone, as the
        report scores them (a compression starts from the FE's unloaded state)."""
        projected, _ = self(traj, step_shapes(traj, step, predicted))
        return projected.unloaded if step == "unloaded" else projected.compressed[0]


def step_shapes(traj: Trajectory, step: str, predicted: NDArray) -> BreastShapes:
    """A breast's predicted shapes (T, N, 3) of ``step`` (``unloaded`` or ``compression``)
    as `BreastShapes`, the other step's shapes, the plates and the thickness (the plates' last
    gap along the lower plate's normal) from the FE trajectory ``traj``."""
    if step not in ("unloaded", "compression"):
        raise ValueError(f"step must be 'unloaded' or 'compression', got {step!r}")
    unloaded = predicted if step == "unloaded" else traj.unloaded
    compressed = traj.compressed if step == "unloaded" else predicted
    lower, upper = traj.plates[-1]
    return BreastShapes(
        unloaded.astype(np.float32),
        compressed[None].astype(np.float32),
        traj.plates[None],
        traj.compression_ratio[None],
        np.array([float((upper[ORIGIN] - lower[ORIGIN]) @ lower[NORMAL])]),
    )
