"""The cohort on Dask distributed: a two-worker LocalCluster writes the local pool's arrays."""

import dataclasses
import json
from pathlib import Path

import pytest
from test_cohort import TINY, _cfg
from test_cohort_simulation import FEW_STEPS

from fem.cohort import run_cohort
from fem.contract.trajectory import Trajectory

ONE_PATIENT = ("n_patients=1", "simulate=true", *TINY, *FEW_STEPS)
BREASTS = ("P0000_L", "P0000_R")


@pytest.fixture(scope="module")
def cohorts(tmp_path_factory) -> dict[str, Path]:
    """The tiny cohort on the local pool and on a two-worker LocalCluster (``workers=2``)."""
    folders = {}
    for executor in ("local", "dask"):
        folders[executor] = tmp_path_factory.mktemp(executor)
        report = run_cohort(_cfg(folders[executor], *ONE_PATIENT, f"executor={executor}"))
        assert report["failures"] == [] and report["simulation"]["n_converged"] == 2
    return folders


def _assert_same_arrays(path: Path, other: Path) -> None:
    """Every field of the two trajectories but the metadata (timings) holds the same bytes."""
    a, b = Trajectory.load(path), Trajectory.load(other)
    for field in dataclasses.fields(Trajectory):
        if field.name != "metadata":
            x, y = getattr(a, field.name), getattr(b, field.name)
            assert (x.dtype, x.shape) == (y.dtype, y.shape), f"{other}: {field.name}"
            assert x.tobytes() == y.tobytes(), f"{other}: {field.name} differs from {path}"


@pytest.mark.parametrize("stage", ["meshes", "trajectories"])
def test_dask_writes_the_local_pools_arrays(cohorts, stage):
    folder = "" if stage == "meshes" else "trajectories"
    for breast in BREASTS:
        _assert_same_arrays(
            cohorts["local"] / folder / f"{breast}.npz", cohorts["dask"] / folder / f"{breast}.npz"
        )


def test_a_resume_on_dask_skips_finished_breasts(cohorts):
    """The local pool's cohort, finished on Dask with another worker count: executor, scheduler
    and workers are no settings of the breasts, and only the missing breast is made."""
    folder = cohorts["local"]
    missing = folder / "trajectories" / "P0000_R.npz"
    missing.unlink()
    stamps = {p: p.stat().st_mtime_ns for p in folder.rglob("P*.npz")}
    report = run_cohort(_cfg(folder, *ONE_PATIENT, "executor=dask", "workers=1"))
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert report["simulation"]["n_converged"] == 2
    _assert_same_arrays(cohorts["dask"] / "trajectories" / "P0000_R.npz", missing)
    recorded = json.loads((folder / "cohort_config.json").read_text())
    assert set(recorded) == {"generator", "mesher", "simulation", "refine", "variation"}
    assert recorded["variation"] is None  # the paper cohort's conditions
