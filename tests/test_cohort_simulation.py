"""The cohort command's simulation stage and `python -m fem.simulate` (few recorded steps)."""

import json

import meshio
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from test_cohort import CONF, _cfg

from fem.breasts.cohort_simulation import (
    REFINED_MIN_VOLUME_RATIO,
    simulate_breast,
    simulate_refined,
)
from fem.breasts.mesh import Mesher
from fem.cohort import run_cohort
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.simulation import PAPER_MATERIALS, Simulation, SimulationFailed
from fem.simulate import simulate_file

FEW_STEPS = ("simulation.unloaded_steps=3", "simulation.compression_steps=4")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("simulated")
    report = run_cohort(_cfg(out, "n_patients=1", "simulate=true", "figures=false", *FEW_STEPS))
    return out, report


def test_trajectories_and_report(simulated):
    out, report = simulated
    sim = report["simulation"]
    assert sim["n_converged"] == 2 and sim["n_failed"] == 0 and sim["reached_target"] == 2
    names = {p.name for p in (out / "trajectories").iterdir()}
    assert {"P0000_L.npz", "P0000_R.npz", "simulation.csv", "simulation.json"} <= names
    assert {"simulation_summary.md", "simulation_summary.png"} <= names
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    traj = Trajectory.load(out / "trajectories" / "P0000_L.npz")
    assert traj.unloaded.shape == (3, traj.n_nodes, 3)
    assert traj.compressed.shape == (4, traj.n_nodes, 3) and traj.plates.shape == (4, 2, 3, 3)
    # The target ratio is reached on the unloaded shape's cranio-caudal extent.
    assert traj.compression_ratio[-1] == pytest.approx(traj.metadata["target_compression_ratio"])
    skin = traj.flagged(NodeFlag.SKIN)
    lower, upper = traj.plates[-1, :, 0, 2]  # the plates' heights (CC: origin z)
    # over the plates: in front of their chest-side edge (nodes on the edge face lie behind)
    covered = traj.compressed[-1][skin, 1] > traj.plates[-1, 0, 0, 1] + 1e-9
    z = traj.compressed[-1][skin[covered], 2]
    assert z.min() >= lower - 1e-9 and z.max() <= upper + 1e-9  # nothing inside a plate
    extent = np.ptp(traj.unloaded[-1][skin, 2])
    assert upper - lower == pytest.approx((1 - traj.compression_ratio[-1]) * extent)
    rows = (out / "trajectories" / "simulation.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("name,status,step,reason")


def test_resume_skips_finished_breasts(simulated):
    out, _ = simulated
    done = out / "trajectories" / "P0000_L.npz"
    stamp = done.stat().st_mtime_ns
    (out / "trajectories" / "P0000_R.npz").unlink()
    report = run_cohort(_cfg(out, "n_patients=1", "simulate=true", "figures=false", *FEW_STEPS))
    assert done.stat().st_mtime_ns == stamp  # finished breasts are not redone
    assert (out / "trajectories" / "P0000_R.npz").exists()
    assert report["simulation"]["n_converged"] == 2


def test_a_resume_with_other_settings_is_refused_before_any_breast(simulated):
    out, _ = simulated
    before = sorted(p.name for p in out.rglob("*"))
    cfg = _cfg(out, "n_patients=2", "simulate=true", "~simulation.materials.gland", *FEW_STEPS)
    with pytest.raises(
        ValueError, match=r"simulation\.materials\.gland\.young: 2500\.0 there, \(none\) now"
    ):
        run_cohort(cfg)
    assert sorted(p.name for p in out.rglob("*")) == before  # nothing written


def test_bad_settings_end_the_command_a_diverging_breast_is_recorded(simulated, tmp_path):
    out, _ = simulated
    mesh = out / "P0000_L.npz"
    no_gland = Simulation(materials={"fat": {"young": 1100.0}, "muscle": {"young": 6000.0}})
    with pytest.raises(ValueError, match="tissue 'gland'"):
        simulate_breast(no_gland, mesh, tmp_path)
    assert not list(tmp_path.iterdir())  # a settings error is no failure of the breast

    class Diverges(Simulation):
        def __call__(self, traj):
            raise SimulationFailed(traj.source, "compression", "Newton did not converge", {})

    row = simulate_breast(Diverges(), mesh, tmp_path)
    failure = json.loads((tmp_path / "P0000_L.failed.json").read_text())
    assert row["status"] == failure["status"] == "failed" and failure["step"] == "compression"
    assert not (tmp_path / "P0000_L.npz").exists()


def test_simulate_command_writes_trajectory_and_time_series(simulated, tmp_path):
    out, _ = simulated
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "simulate",
            overrides=[
                f"input={out / 'P0000_L.npz'}",
                f"output={tmp_path / 'case'}",
                "simulation.friction=0",
                "simulation.compression_ratio=0.3",
                "simulation.unloaded_steps=2",
                "simulation.compression_steps=2",
            ],
        )
    simulate_file(cfg)
    traj = Trajectory.load(tmp_path / "case.npz")
    assert traj.compression_ratio[-1] == pytest.approx(0.3)
    assert traj.metadata["simulation"]["friction"] == 0
    times = meshio.xdmf.TimeSeriesReader(tmp_path / "case.xdmf")
    _, _ = times.read_points_cells()
    assert times.num_steps == 1 + 2 + 2


@pytest.mark.slow
def test_refined_ground_truth_at_the_coarse_nodes(phantom):
    """`simulate_refined`: both steps on the 8x refined mesh, recorded at the coarse mesh's
    nodes and projected onto valid coarse shapes: no covered skin node inside a plate, no
    coarse element below the projection's volume ratio, the rigid muscle still, the checks
    recorded of the coarse elements; element sets are refused."""
    volume, meta = phantom
    coarse = Mesher(target_elements=400, tolerance=100)(volume, meta)
    simulation = Simulation(unloaded_steps=2, compression_steps=3)
    out = simulate_refined(simulation, coarse, 1)
    assert out.unloaded.shape == (2, coarse.n_nodes, 3)
    assert out.compressed.shape == (3, coarse.n_nodes, 3)
    sim = out.metadata["simulation"]
    assert sim["refine_levels"] == 1 and sim["refined_tetrahedra"] == 8 * coarse.n_cells
    assert out.compression_ratio[-1] == pytest.approx(meta["target_compression_ratio"])
    x, start = out.compressed[-1], out.unloaded[-1]
    skin = coarse.flagged(NodeFlag.SKIN)
    for origin, normal, axis in out.plates[-1]:
        covered = (x[skin] - origin) @ axis > 1e-9
        assert ((x[skin[covered]] - origin) @ normal).min() > -1e-9
    ratio = signed_volume(x, coarse.cells) / signed_volume(coarse.points, coarse.cells)
    assert sim["min_element_volume_ratio"] == pytest.approx(ratio.min())
    # the 8x answer inverts a coarse element here; the projection makes every one valid
    projection = sim["projection"]
    assert projection["min_element_volume_ratio_before"] < 0
    assert ratio.min() >= REFINED_MIN_VOLUME_RATIO - 1e-9 and projection["moved_max_mm"] > 0
    muscle = np.setdiff1d(
        coarse.cells[coarse.tissue == Tissue.MUSCLE], coarse.flagged(NodeFlag.MUSCLE_INTERFACE)
    )
    assert np.abs(x[muscle] - start[muscle]).max() == 0.0
    plain = simulation(coarse)  # the coarse mesh's own answer differs
    assert np.abs(plain.compressed[-1] - x).max() > 0.01
    sets = Simulation(materials={**PAPER_MATERIALS, "fat": {"young": 1100.0, "elements": "f.txt"}})
    with pytest.raises(ValueError, match=r"simulation\.materials\.fat\.elements: element sets"):
        simulate_refined(sets, coarse, 1)
