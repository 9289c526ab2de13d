"""Quasi-static equilibrium: Newton's method with a safeguarded line search, and load ramps.

Equilibrium minimises the potential ``Pi(x) = W(x) - f_ext . x`` over the free degrees of
freedom. Each Newton step solves ``K dx = -r`` on the free DOFs; where ``K`` is indefinite and
``dx`` is no descent direction, ``K + tau diag|K|`` is solved instead with ``tau`` raised tenfold
until it is (a Levenberg-Marquardt safeguard); the line search halves the step until no element
is inverted and the potential decreases (Armijo), and where no length of the step does (a
nearly singular ``K``), the damped step is searched instead. A load ramp raises
the load factor in increments predicted from the last equilibria, halving a step whose Newton
iteration fails and growing the increment again after easy steps, and records the positions
at the requested load factors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.linalg import lu_factor, lu_solve
from scipy.sparse.linalg import LinearOperator, cg

from fem.engine.assembly import HyperelasticBody, Model
from fem.engine.linear import (
    Pardiso,
    Tangent,
    add_diagonal,
    constrained,
    factorize,
    resolve_backend,
    submatrix,
    superlu,
)

#: Body force of gravity for water-like tissue: rho g = 1000 kg/m^3 * 9.81 m/s^2 = 9.81e-6 N/mm^3,
#: i.e. 9.81 in the solver's force unit (Pa mm^2 = 1e-6 N) per mm^3.
GRAVITY_FORCE_DENSITY = 9.81


#: Distance from a bound, mm, within which a DOF counts as on it (steps land on a plate only
#: to round-off).
ON_BOUND = 1e-9


class SolverError(RuntimeError):
    """Newton or the load ramp failed; the message says where and why."""


def nodal_body_force(body: HyperelasticBody, force_density: NDArray) -> NDArray[np.float64]:
    """Consistent nodal forces of a uniform body force (a quarter of each element to each node).

    Parameters
    ----------
    force_density : (3,) float
        Force per reference volume, Pa/mm (e.g. ``GRAVITY_FORCE_DENSITY * direction``).

    Returns
    -------
    (3N,) float64
    """
    f = np.zeros((len(body.points), 3))
    np.add.at(
        f, body.cells.ravel(), np.repeat(body.volumes / 4.0, 4)[:, None] * np.asarray(force_density)
    )
    return f.ravel()


@dataclass(frozen=True)
class NewtonSettings:
    """Convergence and safeguard settings.

    Parameters
    ----------
    tolerance : float
        Converged when ``|r_free| <= tolerance * max(|f_ext|, |f_int|)`` (1e-6 and 1e-8 gave
        compressed breasts that differ by 2e-5 mm), ...
    step_tolerance : float
        ... or when a Newton correction moves no node by more than this, mm (needed when
        internal and external forces both vanish at equilibrium, e.g. plates squeezing an
        unloaded body).
    max_iterations : int
        Newton iterations per load increment. A step converges in 2-10; past an instability
        (tissue squeezed out behind a plate's edge at 97 % of the travel, P0006_R) damped
        steps creep on for more than 25 iterations before Newton's convergence returns.
    min_step : float
        Smallest line-search step before the increment is declared failed.
    min_jacobian : float
        Elements with ``det F`` below this count as inverted.
    friction_tolerance : float
        A load step's friction uses the normal forces of its own equilibrium: Newton is
        repeated with the updated forces (`fem.engine.constraints.FramedModel.update_friction`)
        until they change by less than this share of the largest one, ...
    friction_updates : int
        ... at most this many times (the forces of the last step are the first guess).
    max_contraction : float
        Newton first steps with the stored factorization of an earlier tangent (modified
        Newton: no assembly, one back-substitution; held DOFs stay, and DOFs a step would
        carry through a bound are stopped there as `newton_step` does, with that stored
        tangent: 15 % fewer tangents on a 10k-tetrahedra breast); once the residual shrinks
        by less than this factor per step, or the line search would cut such a step, it
        assembles the tangent and factorizes afresh, and goes on with modified steps on that
        new factorization (a third fewer tangents again, compression 15 % faster at 10k
        tetrahedra and at the cohort's size, positions within 1e-5 mm). 0 disables the reuse
        (0.5 against 0: 6 instead of 101 tangents and half the time for a breast's unloaded
        state, positions within 1e-6 mm).
    linear_solver : {"auto", "superlu", "pardiso"}
        Sparse factorization (`fem.engine.linear`): ``auto`` is MKL PARDISO from
        `fem.engine.linear.PARDISO_FROM` DOFs on when the optional ``mkl`` wheel is installed,
        SuperLU otherwise.
    """

    tolerance: float = 1e-6
    step_tolerance: float = 1e-7
    max_iterations: int = 100
    min_step: float = 1.0 / 64
    min_jacobian: float = 1e-3
    friction_tolerance: float = 1e-3
    friction_updates: int = 10
    max_contraction: float = 0.5
    linear_solver: str = "auto"


class ReusedFactorization:
    """Linear solves with held DOFs that reuse one sparse LU factorization across Newton
    iterations, load steps and active sets.

    ``solve(K, b, keep)`` solves ``constrained(K, keep) d = b``. The stored factorization of an
    earlier ``constrained(K0, keep0)`` preconditions a conjugate-gradient solve. DOFs held now
    but free in the factor (nodes that came onto a plate) are removed from it exactly by a
    Schur complement: with ``Z = A0^-1 E`` for their unit vectors ``E`` (one back-substitution
    per DOF, cached while the factor lives), ``z = A0^-1 r - Z (E^T Z)^-1 Z^T r`` is the
    inverse of ``A0`` on the remaining DOFs. DOFs free now but held in the factor get the
    factor's diagonal (`constrained` keeps it). So a growing contact area costs a few
    back-substitutions instead of a factorization per load step. When CG needs more than ``refactor_after`` iterations (the
    tangent has drifted), the next solve factorizes afresh; when it does not reach ``rtol``
    within ``max_iterations``, this one does.

    The factorizations are SuperLU's or MKL PARDISO's (``backend``, `fem.engine.linear`:
    ``auto`` picks by size); PARDISO keeps the analysis of the pattern, which does not change
    along a load path.
    """

    def __init__(
        self,
        rtol: float = 1e-10,
        max_iterations: int = 30,
        refactor_after: int = 15,
        backend: str = "auto",
    ) -> None:
        self.rtol, self.max_iterations, self.refactor_after = rtol, max_iterations, refactor_after
        resolve_backend(backend, 0)  # refuse an unknown one now
        self.backend = backend
        self._pardiso: Pardiso | None = None
        self.lu = None
        self.keep: NDArray[np.bool_] | None = None  # the DOFs free in the factor
        self.matrix: Tangent | None = None  # the tangent factorized (all DOFs free)
        self.columns: dict[int, NDArray] = {}  # DOF j -> A0^-1 e_j
        self.stale = False
        self.factorizations = 0

    def usable(self, n: int) -> bool:
        """Whether a stored, fresh factorization of an ``n``-DOF system can be reused."""
        return self.lu is not None and self.lu.shape == (n, n) and not self.stale

    def preconditioner(self, keep: NDArray[np.bool_]) -> Callable[[NDArray], NDArray]:
        """``r -> z``: the stored factor's inverse on the DOFs ``keep`` (zero elsewhere)."""
        held = np.flatnonzero(self.keep & ~keep)
        Z = S = None
        if held.size:
            missing = [j for j in held if j not in self.columns]
            if missing:
                E = np.zeros((len(keep), len(missing)))
                E[missing, np.arange(len(missing))] = 1.0
                self.columns.update(zip(missing, self.lu.solve(E).T, strict=True))
            Z = np.stack([self.columns[j] for j in held], axis=1)  # (F, H)
            S = lu_factor(Z[held])  # E^T A0^-1 E (LU: A0 may be indefinite)

        def apply(r: NDArray) -> NDArray:
            z = self.lu.solve(r)
            if Z is not None:
                z -= Z @ lu_solve(S, z[held])
            return np.where(keep, z, 0.0)

        return apply

    def solve(
        self, K: Tangent, b: NDArray, keep: NDArray[np.bool_] | None = None
    ) -> NDArray[np.float64]:
        """Solve ``constrained(K, keep) d = b`` (``b`` is zero on the held DOFs)."""
        keep = np.ones(K.shape[0], bool) if keep is None else keep
        A = constrained(K, keep) if not keep.all() else K
        if self.usable(K.shape[0]):
            M = LinearOperator(K.shape, self.preconditioner(keep), dtype=float)
            iterations = 0

            def count(_: NDArray) -> None:
                nonlocal iterations
                iterations += 1

            A_op = LinearOperator(K.shape, A.__matmul__, dtype=float)
            x, info = cg(A_op, b, rtol=self.rtol, maxiter=self.max_iterations, M=M, callback=count)
            self.stale = iterations > self.refactor_after
            if info == 0:
                return x
        self.lu, self.keep, self.columns = self._factorize(A), keep.copy(), {}
        self.matrix = K
        self.stale = False
        self.factorizations += 1
        return self.lu.solve(b)

    def _factorize(self, A: Tangent):  # SuperLU or PardisoFactor: .solve, .shape
        if resolve_backend(self.backend, A.shape[0]) == "superlu":
            return superlu(A)
        self._pardiso = self._pardiso or Pardiso()
        return self._pardiso.factorize(A)


#: Default settings, shared (the dataclass is frozen).
DEFAULT_NEWTON = NewtonSettings()


def newton_step(
    K: sparse.csr_matrix,
    g: NDArray,
    flat: NDArray,
    free: NDArray[np.bool_],
    held: NDArray[np.bool_],
    lower: NDArray | None,
    upper: NDArray | None,
    linear: ReusedFactorization,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Newton correction of the free DOFs that stops at the bounds.

    Solves ``K d = -g`` with the ``held`` DOFs fixed. A DOF the step would carry through its
    bound is then fixed too and the step solved again, until none crosses: onto the bound when
    its own gradient pushes it there (it is falling onto a plate), at its current value
    otherwise. Clipping a plain Newton step instead breaks the step's consistency and the line
    search fails as soon as nodes fall onto a plate. Should the bound moves make the step
    ascend, they are dropped: with every crossing DOF held in place the step is a Newton step
    in a subspace, a descent direction for a positive definite ``K``.

    Parameters
    ----------
    K : (F, F) sparse matrix or `fem.engine.assembly.SplitTangent`
        Tangent of the free DOFs.
    g : (3N,) float
        Gradient of the potential.
    flat : (3N,) float
        Current (feasible) DOF values.
    held : (3N,) bool
        DOFs held on their bounds (the plate pushes them).

    Returns
    -------
    d : (F,) float64
        The step of the free DOFs.
    held : (3N,) bool
        The DOFs the step fixes.
    """
    gf, x = g[free], flat[free]
    fixed = held[free].copy()
    p = np.zeros(len(x))
    for _ in range(20):
        keep = ~fixed
        d = linear.solve(K, np.where(keep, -(gf + K @ p), 0.0), keep)
        d = np.where(keep, d, p)
        if lower is None:
            break
        target = np.clip(x + d, lower[free], upper[free])
        crossing = keep & (np.abs(target - (x + d)) > ON_BOUND)
        if not crossing.any():
            if gf @ d < 0 or not p.any():
                break
            p[:] = 0.0  # the bound moves made the step ascend: hold those DOFs in place
            continue
        fixed |= crossing
        onto = crossing & (gf * (target - x) < 0)  # the gradient pushes it onto the bound
        p[onto] = (target - x)[onto]
    out = np.zeros_like(free)
    out[free] = fixed
    return d, out


#: Largest Levenberg-Marquardt shift ``tau`` (`damped_step`) before Newton gives up.
MAX_SHIFT = 1e3


def damped_step(
    K: Tangent, held: NDArray[np.bool_], r: NDArray, shift: float, backend: str = "auto"
) -> NDArray:
    """Levenberg-Marquardt step ``-(K + tau diag|K|)^-1 r`` with the ``held`` DOFs fixed: for
    ``tau`` large enough a descent direction of bounded length however indefinite or nearly
    singular ``K`` is, (F,) float64. Factorized by ``backend`` (`fem.engine.linear`), apart
    from the factorization Newton reuses."""
    shifted = constrained(add_diagonal(K, shift * np.abs(K.diagonal())), ~held)
    return factorize(shifted, backend).solve(-np.where(held, 0.0, r))


def newton(
    body: HyperelasticBody | Model,
    x: NDArray,
    free: NDArray[np.bool_],
    f_ext: NDArray,
    settings: NewtonSettings = DEFAULT_NEWTON,
    linear: ReusedFactorization | None = None,
) -> tuple[NDArray[np.float64], int, NDArray[np.float64]]:
    """Equilibrium positions from the start ``x`` (N, 3); fixed DOFs keep their values.

    When ``body`` has bounds (`fem.engine.constraints.FramedModel.bounds`: rigid plates), the free DOFs are projected onto
    them and the equilibrium is the minimum of the potential over that box: projected Newton
    with an active set. A DOF on a bound whose gradient pushes it out of the box is held for
    the iteration (its multiplier has the right sign), one that would move inside is released,
    and the step stops DOFs at the bounds they would cross (`newton_step`); line-search trials
    are projected onto the box.

    Returns
    -------
    x : (N, 3) float64
    iterations : int
    gradient : (3N,) float64
        ``dPi/dx`` at ``x`` (internal minus external forces: the reactions on fixed and held
        DOFs), for parts that lag contact forces.

    Raises
    ------
    SolverError
        No convergence, or the line search could not find an admissible descent step.
    """
    x = np.array(x, float)
    lower = upper = None
    if hasattr(body, "bounds"):
        lower, upper = body.bounds(x)
        lower[~free], upper[~free] = -np.inf, np.inf
        if np.isneginf(lower).all() and np.isposinf(upper).all():
            lower = upper = None
    flat = x.reshape(-1)
    if lower is not None:
        flat = np.clip(flat, lower, upper)
        x = flat.reshape(x.shape)
    linear = linear or ReusedFactorization(backend=settings.linear_solver)

    def potential(y: NDArray) -> float:
        return body.energy(y) - f_ext @ y.reshape(-1)

    def admissible(y: NDArray) -> bool:
        return body.min_jacobian(y) > settings.min_jacobian

    if not admissible(x):
        raise SolverError("the start (projected onto the bounds) has inverted elements")

    pi = potential(x)
    reuse = settings.max_contraction > 0  # modified Newton steps allowed
    previous = np.inf  # residual norm before the last modified step
    for it in range(settings.max_iterations):
        g = body.internal_force(x) - f_ext
        held = np.zeros_like(free)
        if lower is not None:  # DOFs on a bound that pushes back carry a contact force
            held = free & (
                ((flat <= lower + ON_BOUND) & (g > 0)) | ((flat >= upper - ON_BOUND) & (g < 0))
            )
        r = np.where(held, 0.0, g)[free]
        norm = np.linalg.norm(r)
        scale = max(np.linalg.norm(f_ext[free]), np.linalg.norm((g + f_ext)[free]), 1e-30)
        if norm <= settings.tolerance * scale:
            return x, it, g
        if norm > settings.max_contraction * previous:  # modified steps stall: refactorize
            reuse, linear.stale = False, True
        modified = reuse and linear.lu is not None and linear.lu.shape == (r.size, r.size)
        if modified:  # a step with an earlier tangent's factorization: no assembly
            dx, previous = linear.preconditioner(~held[free])(-r), norm
            trial = flat[free] + dx
            if lower is not None and not (
                np.all(trial >= lower[free] - ON_BOUND) and np.all(trial <= upper[free] + ON_BOUND)
            ):  # ... that would carry DOFs through a bound: stop them there, same tangent
                dx, held = newton_step(linear.matrix, g, flat, free, held, lower, upper, linear)
            slope = g[free] @ dx
            modified = slope < 0
        if not modified:
            K = submatrix(body.tangent(x), free)
            factorized = linear.factorizations
            dx, held = newton_step(K, g, flat, free, held, lower, upper, linear)
            slope, previous = g[free] @ dx, np.inf
            reuse |= linear.factorizations > factorized and settings.max_contraction > 0
        shift = 1e-3
        while slope >= 0 and not modified:  # indefinite tangent (buckling skin): shift it
            dx = damped_step(K, held[free], r, shift, linear.backend)
            shift *= 10
            slope = g[free] @ dx
        step, rejected = 1.0, False
        while True:
            trial = flat.copy()
            trial[free] += step * dx
            if lower is not None:
                trial = np.clip(trial, lower, upper)
            decrease = min(g @ (trial - flat), 0.0)
            trial_x = trial.reshape(x.shape)
            if admissible(trial_x):
                pi_trial = potential(trial_x)
                if pi_trial <= pi + 1e-4 * decrease + 1e-12 * abs(pi):
                    break
            if modified:  # no cutting a modified step: assemble the tangent instead
                reuse, linear.stale, rejected = False, True, True
                break
            step *= 0.5
            if step < settings.min_step:
                if shift > MAX_SHIFT:
                    raise SolverError(
                        f"line search failed at Newton iteration {it} (|r| = {norm:.3g})"
                    )
                # No length of this step descends admissibly (a nearly singular tangent sends
                # a node 100 mm away): damp the tangent, as a trust region would.
                dx = damped_step(K, held[free], r, shift, linear.backend)
                shift, step = 10 * shift, 1.0
        if rejected:
            continue
        moved = np.abs(trial - flat).max()
        x, flat, pi = trial_x, trial, pi_trial
        if step == 1.0 and moved <= settings.step_tolerance:
            return x, it + 1, body.internal_force(x) - f_ext
    raise SolverError(f"Newton did not converge in {settings.max_iterations} iterations")


def extrapolate(path: Sequence[tuple[float, NDArray]], load: float) -> NDArray[np.float64]:
    """The Lagrange polynomial through the equilibria ``path`` ((load factor, positions (N, 3))
    pairs, at most three: constant, linear or quadratic) evaluated at ``load``: the predictor
    of a load step (quadratic instead of linear: 235 instead of 309 Newton iterations for a
    breast's 100 unloaded-state steps, P0153_L)."""
    guess = np.zeros_like(path[-1][1])
    for i, (t_i, x_i) in enumerate(path):
        weight = 1.0
        for j, (t_j, _) in enumerate(path):
            if j != i:
                weight *= (load - t_j) / (t_i - t_j)
        guess += weight * x_i
    return guess


def load_ramp(
    body: HyperelasticBody | Model,
    x0: NDArray,
    free: NDArray[np.bool_],
    load: Callable[[float], NDArray],
    record: Sequence[float],
    settings: NewtonSettings = DEFAULT_NEWTON,
    max_cutbacks: int = 10,
    configure: Callable[[float], None] | None = None,
    prescribed: Callable[[float], NDArray] | None = None,
) -> NDArray[np.float64]:
    """Follow the equilibrium path from load factor 0 to ``max(record)``.

    Parameters
    ----------
    load : callable
        Load factor -> external force vector (3N,).
    record : sequence of float
        Increasing load factors at which the positions are recorded (each one is reached
        exactly; increments between them adapt).
    configure : callable, optional
        Called with the load factor before each solve, to move prescribed boundaries (plates).
    prescribed : callable, optional
        Load factor -> positions (N, 3) whose fixed DOFs (``~free``) are imposed at that load
        factor (prescribed displacements); without it fixed DOFs keep their ``x0`` values.

    Returns
    -------
    (len(record), N, 3) float64
        Positions at the recorded load factors.
    """
    x = np.array(x0, float)
    lam, increment = 0.0, float(record[0])
    path = [(lam, x)]  # the last three equilibria: the predictor
    linear = ReusedFactorization(backend=settings.linear_solver)
    out = []
    for target in record:
        cutbacks = 0
        while lam < target - 1e-12:
            nxt = min(lam + increment, target)
            guess = extrapolate(path, nxt)
            if body.min_jacobian(guess) <= settings.min_jacobian:
                guess = x.copy()
            fixed = x if prescribed is None else prescribed(nxt)  # exactly, not extrapolated
            guess.reshape(-1)[~free] = fixed.reshape(-1)[~free]
            if configure is not None:
                configure(nxt)
            if hasattr(body, "predict"):  # e.g. the friction's normal forces
                body.predict(nxt - lam)
            try:
                x_new, iterations, gradient = newton(body, guess, free, load(nxt), settings, linear)
                for _ in range(
                    settings.friction_updates if hasattr(body, "update_friction") else 0
                ):
                    if body.update_friction(x_new, gradient) <= settings.friction_tolerance:
                        break
                    x_new, _, gradient = newton(body, x_new, free, load(nxt), settings, linear)
            except SolverError as exc:
                if hasattr(body, "reject"):
                    body.reject()
                cutbacks += 1
                increment = 0.5 * (nxt - lam)  # of the failed step: the increment may be larger
                if cutbacks > max_cutbacks:
                    raise SolverError(
                        f"load factor {nxt:.4g}: {exc}; gave up after {max_cutbacks} cutbacks"
                    ) from exc
                continue
            if hasattr(body, "accept"):
                body.accept(x_new, gradient, nxt - lam)
            x, lam = x_new, nxt
            path = [*path[-2:], (lam, x)]
            if iterations <= 4:
                increment *= 1.5
        out.append(x.copy())
        increment = max(increment, 1e-3)
    return np.stack(out)
