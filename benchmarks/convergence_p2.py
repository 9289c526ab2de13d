"""Convergence study: P1 tetrahedra (plain, nodal-averaged, production) against quadratic ones.

A hemisphere of fat (radius 50 mm, E = 1100 Pa, nu = 0.495) is clamped by its flat face to a
vertical wall (the plane z = 0, a chest wall) and sags under gravity acting along -y, parallel
to the wall: a standing, bending-dominated breast-like problem, where volumetric locking shows
most. The load is ramped to 0.25 g (moderate strains) and on to 1 g (large strains). By
symmetry only the half x >= 0 is meshed, with ``u_x = 0`` on the plane x = 0.

The meshes are nested (`fem.engine.reference.hemisphere`: every level splits each tetrahedron of the
previous one into eight, on the same polyhedron), so the only error is the discretisation.
For each level the script solves

* P1 plain (``averaging="element"``), P1 nodal-averaged (``stabilization=0``) and the
  production setting (nodal, ``stabilization=0.1``) with `fem.engine.solver.load_ramp`;
* the Taylor-Hood P2-P1 reference (`fem.engine.reference`, the finest level is the reference) and,
  on the coarser levels, pure P2 displacement, to show how much P2 alone still locks;

and prints markdown tables of the apex sag (-u_y of the vertex at (0, 0, 50), mm) and of the
compliance ``int b . u dV`` of the whole hemisphere (mJ), with the errors relative to the
finest Taylor-Hood solution and its Richardson extrapolation.

Run from the repository root (about 4 minutes on 2 cores)::

    nice -n 10 python benchmarks/convergence_p2.py

Options: ``--p1-levels 3 --th-levels 3 --p2-levels 2`` (numbers of levels from the coarsest,
these are the defaults); ``--p1-levels 4`` adds the P1 level 3 (65536 tetrahedra in the half,
33296 free DOFs), which did not finish within 15 minutes on 2 shared cores (factorizing the
nodal-averaged tangents).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass
from unittest import mock

import numpy as np
from scipy.sparse.linalg import splu

import fem.engine.solver
from fem.engine import reference as ref
from fem.engine.assembly import HyperelasticBody
from fem.engine.material import lame_parameters
from fem.engine.solver import GRAVITY_FORCE_DENSITY, load_ramp, nodal_body_force

RADIUS = 50.0  # mm
YOUNG, POISSON = 1100.0, 0.495  # fat, Pa
LOAD_FACTORS = (0.25, 1.0)  # fractions of g
GRAVITY = np.array([0.0, -GRAVITY_FORCE_DENSITY, 0.0])  # Pa/mm, along -y (parallel to the wall)
P1_VARIANTS = {  # label: (averaging, stabilization)
    "P1 plain": ("element", 0.0),
    "P1 nodal": ("nodal", 0.0),
    "P1 nodal+0.1": ("nodal", 0.1),
}
MJ_PER_PA_MM3 = 1e-6  # 1 Pa mm^3 = 1e-9 J


@dataclass
class Result:
    """One solve: apex sag (mm) and whole-hemisphere compliance (mJ) per load factor."""

    method: str
    level: int
    dofs: int
    seconds: float
    sag: np.ndarray
    compliance: np.ndarray


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else what `platform` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def apex_vertex(points: np.ndarray) -> int:
    """Index of the vertex at (0, 0, RADIUS); points (N, 3), mm."""
    return int(np.argmin(np.linalg.norm(points - [0.0, 0.0, RADIUS], axis=1)))


def splu_without_pivoting(A, permc_spec=None, options=None, **kwargs):
    """`scipy.sparse.linalg.splu` with ``DiagPivotThresh = 0``: no partial pivoting, so the
    symmetric minimum-degree ordering survives. On the level-3 tangents this factorizes in
    9 s (plain P1) instead of 469 s with `fem.engine.solver`'s default pivoting; Newton's residual
    test is unchanged, so the converged solutions are the same."""
    options = {**(options or {}), "SymmetricMode": True, "DiagPivotThresh": 0.0}
    return splu(A, permc_spec=permc_spec, options=options, **kwargs)


def solve_p1(level: int, label: str) -> Result:
    """A P1 variant of `P1_VARIANTS` on the hemisphere of ``level`` (`fem.engine.solver.load_ramp`
    with `splu_without_pivoting` as its factorization)."""
    averaging, stabilization = P1_VARIANTS[label]
    points, cells = ref.oriented_cells(ref.hemisphere(RADIUS, level, half=True))
    mu, kappa = lame_parameters(YOUNG, POISSON)
    start = time.perf_counter()
    body = HyperelasticBody(
        points, cells, mu, kappa, averaging=averaging, stabilization=stabilization
    )
    free = np.ones_like(points, dtype=bool)
    free[np.isclose(points[:, 2], 0.0)] = False  # clamped to the wall
    free[np.isclose(points[:, 0], 0.0), 0] = False  # symmetry plane
    f = nodal_body_force(body, GRAVITY)
    with mock.patch.object(fem.engine.solver, "splu", splu_without_pivoting):
        x = load_ramp(body, points, free.ravel(), lambda s: s * f, LOAD_FACTORS)
    seconds = time.perf_counter() - start
    u = x - points
    apex = apex_vertex(points)
    compliance = 2 * np.array([s * f @ ui.ravel() for s, ui in zip(LOAD_FACTORS, u, strict=True)])
    return Result(
        label, level, int(free.sum()), seconds, -u[:, apex, 1], compliance * MJ_PER_PA_MM3
    )


def solve_reference(level: int, formulation: str) -> Result:
    """Taylor-Hood or pure P2 on the hemisphere of ``level``."""
    mesh = ref.hemisphere(RADIUS, level, half=True)
    mu, kappa = lame_parameters(YOUNG, POISSON)
    start = time.perf_counter()
    disc = ref.discretize(mesh, float(mu), float(kappa), formulation)
    fixed = np.union1d(
        ref.dofs_where(disc, lambda x: np.isclose(x[2], 0.0)),
        ref.dofs_where(disc, lambda x: np.isclose(x[0], 0.0), components=[0]),
    )
    sol = ref.solve(disc, fixed, LOAD_FACTORS, body_force=GRAVITY)
    seconds = time.perf_counter() - start
    apex = apex_vertex(mesh.p.T)
    compliance = 2 * np.array(
        [
            s * ref.compliance(disc, u, GRAVITY)
            for s, u in zip(LOAD_FACTORS, sol.displacement, strict=True)
        ]
    )
    label = "P2-P1 (Taylor-Hood)" if formulation == "taylor-hood" else "P2"
    print(
        f"  {label} level {level}: {sol.newton_iterations} Newton iterations, "
        f"{sol.factorizations} factorizations",
        flush=True,
    )
    dofs = disc.n_u + disc.n_p - len(fixed)
    return Result(
        label, level, dofs, seconds, -sol.displacement[:, apex, 1], compliance * MJ_PER_PA_MM3
    )


def richardson(values: np.ndarray) -> tuple[float, float] | None:
    """Extrapolated limit and observed order of the last three values of a sequence on meshes
    halving h; None unless the differences shrink monotonically (a clean asymptotic range)."""
    a0, a1, a2 = values[-3:]
    d1, d2 = a1 - a0, a2 - a1
    if d1 == 0 or d2 / d1 <= 0 or abs(d2) >= abs(d1):
        return None
    order = np.log2(d1 / d2)
    return a2 + d2 / (2**order - 1), float(order)


def table(results: list[Result], quantity: str, load: int, reference: float) -> str:
    """Markdown table: one row per level, one column per method, value and relative error."""
    methods = list(dict.fromkeys(r.method for r in results))
    levels = sorted({r.level for r in results})
    lines = [
        "| level | tets (half) | " + " | ".join(methods) + " |",
        "| --- | --- | " + " | ".join("---" for _ in methods) + " |",
    ]
    for level in levels:
        cells = []
        for method in methods:
            match = [r for r in results if r.method == method and r.level == level]
            if not match:
                cells.append("-")
                continue
            value = getattr(match[0], quantity)[load]
            cells.append(f"{value:.4g} ({100 * (value / reference - 1):+.2f} %)")
        n_tets = 128 * 8**level
        lines.append(f"| {level} | {n_tets} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--p1-levels", type=int, default=3)
    parser.add_argument("--th-levels", type=int, default=3)
    parser.add_argument("--p2-levels", type=int, default=2)
    args = parser.parse_args()
    print(f"# machine: {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    results: list[Result] = []
    for level in range(max(args.p1_levels, args.th_levels, args.p2_levels)):
        if level < args.th_levels:
            results.append(solve_reference(level, "taylor-hood"))
        if level < args.p2_levels:
            results.append(solve_reference(level, "p2"))
        if level < args.p1_levels:
            results.extend(solve_p1(level, label) for label in P1_VARIANTS)
        for r in results:
            if r.level == level:
                print(
                    f"  level {level} {r.method}: {r.dofs} free DOFs, {r.seconds:.1f} s, "
                    f"sag {r.sag.round(3)} mm, compliance {r.compliance.round(4)} mJ",
                    flush=True,
                )
    print("\n## Run times\n")
    print("| method | level | free DOFs | seconds |\n| --- | --- | --- | --- |")
    for r in results:
        print(f"| {r.method} | {r.level} | {r.dofs} | {r.seconds:.1f} |")
    th = [r for r in sorted(results, key=lambda r: r.level) if r.method.startswith("P2-P1")]
    for load, factor in enumerate(LOAD_FACTORS):
        for quantity, name in (("sag", "apex sag, mm"), ("compliance", "compliance, mJ")):
            values = np.array([getattr(r, quantity)[load] for r in th])
            finest = values[-1]
            extrapolated = richardson(values) if len(values) >= 3 else None
            print(f"\n## {factor:g} g: {name}\n")
            print(f"Reference: Taylor-Hood level {th[-1].level} = {finest:.5g}", end="")
            if extrapolated is not None:
                print(
                    f"; Richardson extrapolation {extrapolated[0]:.5g} "
                    f"(observed order {extrapolated[1]:.2f} in h)",
                    end="",
                )
            print(". Cells: value (error relative to the finest Taylor-Hood level).\n")
            print(table(results, quantity, load, finest))


if __name__ == "__main__":
    main()
