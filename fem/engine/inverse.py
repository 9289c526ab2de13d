"""The inverse unloaded state: the stress-free shape that prone gravity deforms into the image.

`fem.engine.simulation.unloaded_state` estimates the unloaded shape by the simple reversal: the imaged
(prone, gravity-loaded) shape is taken as stress-free and a posterior body force is applied.
That is only a first-order estimate, because the imaged shape is not stress-free. The true
unloaded shape ``X`` solves the inverse problem ``forward(X) = x_img``, where ``forward(X)`` is
the equilibrium of the body with stress-free reference ``X`` under prone gravity (+y body force,
the chest wall of `fem.engine.boundary.chest_wall` on the imaged shape).

It is found by the backward-displacement fixed point (Sellier 2011, "An iterative method for
the inverse elasto-static problem"; used for prone breast MRI by Eiben et al. and Rajagopal et
al.)::

    X_0 = x_img
    x_k = forward(X_k)
    X_{k+1} = X_k + omega_k (x_img - x_k)

with ``omega_k = 1`` (plain iteration) or Aitken's dynamic relaxation (Irons and Tuck 1969;
Kuettler and Wall 2008), until the largest node error ``|x_k - x_img|`` is below a tolerance.
The first two forward solves ramp gravity from zero; each later one starts from the previous
equilibrium shifted by the update (the same displacement field on the new reference) and
continues the load from the residual of that guess to full gravity, which takes a few Newton
iterations instead of a full ramp (and falls back to the full ramp when it fails).

Units mm and Pa, coordinates RAS+ (y anteroposterior, anterior +y).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from fem.contract.quality import signed_volume
from fem.contract.trajectory import Trajectory
from fem.engine.assembly import Model
from fem.engine.boundary import (
    AP_AXIS,
    FASCIA_STIFFNESS,
    ChestWallFascia,
    chest_wall,
    chest_wall_fascia,
)
from fem.engine.constraints import NodeFrames, equilibrium_path
from fem.engine.simulation import PAPER_MATERIALS, Material, breast_model
from fem.engine.solver import (
    DEFAULT_NEWTON,
    GRAVITY_FORCE_DENSITY,
    NewtonSettings,
    SolverError,
    nodal_body_force,
)

#: Load-increment halvings allowed when continuing from a guess before the full ramp is used.
CONTINUATION_CUTBACKS = 2

#: Bounds of the Aitken relaxation factor (a factor outside them signals a noisy estimate).
OMEGA_BOUNDS = (0.1, 2.0)


class InverseError(RuntimeError):
    """An iterate of the inverse unloaded state is unusable (inverted element, failed solve)."""


@dataclass
class InverseResult:
    """Outcome of `inverse_unloaded_state`.

    Attributes
    ----------
    points : (N, 3) float64
        Estimated unloaded (stress-free) shape ``X``, mm: the last iterate whose forward solve
        was computed, so ``residuals[-1]`` is its error.
    loaded : (N, 3) float64
        ``forward(points)``: ``points`` loaded by prone gravity, mm.
    iterations : int
        Number of fixed-point updates ``X_k -> X_{k+1}`` (forward solves: ``iterations + 1``).
    residuals : list of float
        Largest node distance ``max_i |x_k - x_img|``, mm, for ``k = 0 .. iterations``;
        ``residuals[0]`` is the largest sag of the imaged shape taken as reference.
    converged : bool
        ``residuals[-1] < tolerance``.
    relaxation : list of float
        Relaxation factor ``omega_k`` of each update.
    """

    points: NDArray[np.float64]
    loaded: NDArray[np.float64]
    iterations: int
    residuals: list[float] = field(default_factory=list)
    converged: bool = False
    relaxation: list[float] = field(default_factory=list)


def max_node_distance(a: NDArray, b: NDArray) -> float:
    """Largest Euclidean distance between corresponding nodes of two (N, 3) arrays, mm."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1).max())


def prone_gravity(direction_sign: float = 1.0) -> NDArray[np.float64]:
    """Force density (3,) of gravity along ``direction_sign`` * y, Pa/mm (prone: +1, anterior)."""
    density = np.zeros(3)
    density[AP_AXIS] = direction_sign * GRAVITY_FORCE_DENSITY
    return density


def check_orientation(traj: Trajectory, reference: NDArray, iteration: int) -> None:
    """Raise `InverseError` when an element of the reference ``reference`` (N, 3) is inverted.

    Raises
    ------
    InverseError
        Some element has a signed volume <= 0 (mm^3).
    """
    volume = signed_volume(reference, traj.cells)
    bad = int((volume <= 0).sum())
    if bad:
        source = traj.source
        raise InverseError(
            f"{source}: the unloaded-shape iterate X_{iteration} inverts {bad} of {len(volume)} "
            f"elements (smallest signed volume {volume.min():.3g} mm^3); the fixed point diverges "
            "(try relaxation or a stiffer material)"
        )


def forward(
    traj: Trajectory,
    reference: NDArray,
    frames: NodeFrames,
    materials: Mapping[str, Material],
    n_load_steps: int,
    force_density: NDArray,
    guess: NDArray | None = None,
    settings: NewtonSettings = DEFAULT_NEWTON,
    fascia: ChestWallFascia | None = None,
) -> NDArray[np.float64]:
    """Equilibrium of the body with stress-free ``reference`` (N, 3) under a body force.

    Parameters
    ----------
    frames : NodeFrames
        The chest wall's held directions; held coordinates keep their values in ``reference``.
    force_density : (3,) float
        Body force per reference volume, Pa/mm.
    guess : (N, 3) float, optional
        A nearby deformed shape (equal to ``reference`` on the fixed DOFs). The load is then
        continued from the internal force of the guess to the body force in one adaptive ramp
        step; without a guess, or if that fails, the body force is ramped from zero in
        ``n_load_steps`` recorded steps.
    fascia : ChestWallFascia, optional
        The sliding chest wall's fascia, anchored on ``reference``.

    Returns
    -------
    (N, 3) float64
        Deformed positions, mm.

    Raises
    ------
    SolverError
        The load ramp failed.
    """
    moved = replace(traj, points=np.asarray(reference, float))
    model = breast_model(moved, materials, fascia=fascia)
    f = nodal_body_force(model.body, force_density)
    if guess is not None and model.min_jacobian(guess) > settings.min_jacobian:
        try:
            return _continue_from(model, guess, frames, f, settings)
        except SolverError:
            pass  # fall back to the full ramp from the reference
    record = np.arange(1, n_load_steps + 1) / n_load_steps
    return equilibrium_path(model, frames, moved.points, lambda s: s * f, record, settings)[-1]


def _continue_from(
    model: Model, guess: NDArray, frames: NodeFrames, f: NDArray, settings: NewtonSettings
) -> NDArray[np.float64]:
    """Equilibrium under ``f`` from ``guess`` by the homotopy ``(1 - s) f_int(guess) + s f``.

    ``guess`` is in equilibrium at ``s = 0`` on the free DOFs. Gives up after
    `CONTINUATION_CUTBACKS` halvings of the load increment: a guess that far off is better
    replaced by the full ramp from the reference."""
    f0 = model.internal_force(np.asarray(guess, float))
    return equilibrium_path(
        model,
        frames,
        guess,
        lambda s: (1.0 - s) * f0 + s * f,
        [1.0],
        settings,
        max_cutbacks=CONTINUATION_CUTBACKS,
    )[-1]


def aitken_factor(omega: float, previous: NDArray, current: NDArray) -> float:
    """Aitken's dynamic relaxation factor from the last two residual vectors (3N,).

    ``omega_{k} = -omega_{k-1} r_{k-1} . (r_k - r_{k-1}) / |r_k - r_{k-1}|^2``, clipped to
    `OMEGA_BOUNDS`.
    """
    delta = current - previous
    denominator = float(delta @ delta)
    if denominator == 0.0:
        return omega
    return float(np.clip(-omega * float(previous @ delta) / denominator, *OMEGA_BOUNDS))


def inverse_unloaded_state(
    traj: Trajectory,
    materials: Mapping[str, Material] = PAPER_MATERIALS,
    tolerance: float = 0.01,
    max_iterations: int = 30,
    n_load_steps: int = 10,
    relaxation: str = "aitken",
    force_density: float = GRAVITY_FORCE_DENSITY,
    settings: NewtonSettings = DEFAULT_NEWTON,
    chest: str = "sliding",
    fascia: float = FASCIA_STIFFNESS,
) -> InverseResult:
    """The unloaded shape that prone gravity deforms into the imaged shape (backward displacement).

    Parameters
    ----------
    traj : Trajectory
        Mesh whose ``points`` (N, 3) are the imaged prone shape ``x_img``, mm.
    materials : mapping
        Tissue parameters (as for `fem.engine.simulation.unloaded_state`; ``"skin"`` adds the membrane).
    tolerance : float
        Converged when no node of ``forward(X)`` is farther than this from ``x_img``, mm.
    max_iterations : int
        Most fixed-point updates (forward solves: one more).
    n_load_steps : int
        Recorded steps of the gravity ramp of the first forward solve (and of any fallback).
    relaxation : {"aitken", "none"}
        Aitken's dynamic relaxation of the update, or the plain fixed point (``omega = 1``).
    force_density : float
        Magnitude of the prone body force ``rho g`` along +y, Pa/mm.
    chest : str
        The chest-wall condition (`fem.engine.boundary.chest_wall`).
    fascia : float
        The sliding chest wall's tangential stiffness per unit area, Pa/mm
        (`fem.engine.boundary.ChestWallFascia`, anchored on each iterate).

    Returns
    -------
    InverseResult
        ``converged`` is false when ``max_iterations`` updates did not reach ``tolerance``.

    Raises
    ------
    InverseError
        An iterate inverts an element, or a forward solve fails.
    ValueError
        Unknown ``relaxation``; tissue without material; mesh without interface nodes.
    """
    if relaxation not in ("aitken", "none"):
        raise ValueError(f"relaxation must be 'aitken' or 'none', got {relaxation!r}")
    source = traj.source
    target = np.asarray(traj.points, float)
    # One chest wall for all iterates (`fem.engine.boundary.chest_wall`, sliding), its normals
    # on the imaged shape. Held coordinates never move, so they stay at their imaged values.
    frames = NodeFrames.build(traj.n_nodes, chest_wall(traj, target, chest))
    density = prone_gravity() * force_density / GRAVITY_FORCE_DENSITY

    def solve(reference: NDArray, guess: NDArray | None, k: int) -> NDArray:
        try:
            support = chest_wall_fascia(traj, reference, chest, fascia)
            return forward(
                traj, reference, frames, materials, n_load_steps, density, guess, settings, support
            )
        except SolverError as exc:
            raise InverseError(f"{source}: forward solve of iterate X_{k} failed: {exc}") from exc

    reference = target.copy()
    loaded = solve(reference, None, 0)
    residual = target - loaded
    residuals = [float(np.linalg.norm(residual, axis=1).max())]
    omegas: list[float] = []
    omega, previous = 1.0, None
    k = 0
    while residuals[-1] >= tolerance and k < max_iterations:
        if relaxation == "aitken" and previous is not None:
            omega = aitken_factor(omega, previous.ravel(), residual.ravel())
        step = omega * residual
        k += 1
        reference = reference + step
        check_orientation(traj, reference, k)
        # The first update moves the reference by the whole sag: ramp its load from zero.
        loaded = solve(reference, loaded + step if k > 1 else None, k)
        previous, residual = residual, target - loaded
        residuals.append(float(np.linalg.norm(residual, axis=1).max()))
        omegas.append(omega)
    return InverseResult(
        points=reference,
        loaded=loaded,
        iterations=k,
        residuals=residuals,
        converged=residuals[-1] < tolerance,
        relaxation=omegas,
    )
