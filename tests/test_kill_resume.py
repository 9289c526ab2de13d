"""A cohort killed three times (SIGKILL, at random points) resumes to the arrays of an
uninterrupted run, and no worker outlives a killed command."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from fem.contract.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = (
    "n_patients=2",
    "workers=2",
    "figures=false",
    "mesher.target_elements=700",
    "mesher.tolerance=200",
    "simulation.unloaded_steps=4",
    "simulation.compression_steps=5",
)


def _cohort(out: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fem.cohort", f"out_dir={out}", *SETTINGS],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def _processes_writing(out: Path) -> list[int]:
    """PIDs of live processes whose command line names ``out`` (the command and its workers)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().decode(errors="replace")
            state = (proc / "stat").read_text().split()[2]
        except OSError:
            continue
        if proc.name.isdigit() and str(out) in cmd and state != "Z":
            pids.append(int(proc.name))
    return pids


def _arrays(folder: Path) -> dict[str, dict[str, np.ndarray]]:
    return {
        p.name: {f.name: getattr(t, f.name) for f in fields(Trajectory) if f.name != "metadata"}
        for p in sorted(folder.glob("P*.npz"))
        for t in [Trajectory.load(p)]
    }


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_three_kills_then_resume_equal_an_uninterrupted_run(tmp_path):
    rng = random.Random(0)
    killed = tmp_path / "killed"
    for _ in range(3):
        proc = _cohort(killed)
        time.sleep(rng.uniform(2.0, 8.0))
        os.kill(proc.pid, signal.SIGKILL)  # the command only: its workers must follow alone
        proc.wait()
        deadline = time.monotonic() + 10
        while _processes_writing(killed) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _processes_writing(killed), "a worker outlived the killed command"
    assert _cohort(killed).wait() == 0
    clean = tmp_path / "clean"
    assert _cohort(clean).wait() == 0
    for stage in ("", "trajectories"):
        got, expected = _arrays(killed / stage), _arrays(clean / stage)
        assert sorted(got) == sorted(expected) and len(got) == 4
        for name, arrays in expected.items():
            for field, value in arrays.items():
                np.testing.assert_array_equal(got[name][field], value, err_msg=f"{name} {field}")
