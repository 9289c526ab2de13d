import json
from pathlib import Path

import meshio
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from fem.cohort import run_cohort
from fem.contract.trajectory import Trajectory

CONF = str(Path(__file__).resolve().parents[1] / "conf")
#: Overrides of a fast cohort: 500-900 tetrahedra per breast, no pictures.
TINY = ("mesher.target_elements=700", "mesher.tolerance=200", "figures=false")


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(
            "cohort",
            overrides=[
                f"out_dir={out_dir}",
                "n_patients=2",
                "workers=2",
                "simulate=false",
                *overrides,
            ],
        )


@pytest.fixture(scope="module")
def cohort_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cohort")
    report = run_cohort(_cfg(out))
    assert report["failures"] == [] and report["n_breasts_finished"] == 4
    return out


def test_outputs(cohort_dir):
    names = sorted(p.name for p in cohort_dir.iterdir() if p.is_file())
    for b in ("P0000_L", "P0000_R", "P0001_L", "P0001_R"):
        assert {f"{b}.npz", f"{b}.vtu", f"{b}.png"} <= set(names)
    assert {"cohort.csv", "cohort.json", "cohort_summary.png", "cohort_summary.md"} <= set(names)
    assert (
        "| tetrahedra per mesh: min / median / max |"
        in (cohort_dir / "cohort_summary.md").read_text()
    )
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    vtu = meshio.read(cohort_dir / "P0000_L.vtu")
    assert "tissue" in vtu.cell_data and "tissue_code" in vtu.point_data
    traj = Trajectory.load(cohort_dir / "P0000_L.npz")
    assert len(vtu.cells_dict["tetra"]) == traj.n_cells
    report = json.loads((cohort_dir / "cohort.json").read_text())
    assert report["n_inverted"] == 0
    assert 2000 <= report["elements"]["min"] <= report["elements"]["max"] <= 2500
    assert report["volume_error"]["max_abs"] < 0.05
    lines = (cohort_dir / "cohort.csv").read_text().splitlines()
    assert len(lines) == 5 and lines[0].startswith("patient,laterality,site")


def test_resume_redoes_only_unfinished(cohort_dir):
    finished = cohort_dir / "P0001_R.npz"
    before = {p.name: p.stat().st_mtime_ns for p in cohort_dir.glob("P*.npz")}
    finished.unlink()
    (cohort_dir / ".P0001_R.999.tmp.npz").write_bytes(b"half-written")  # a killed run's leftover
    report = run_cohort(_cfg(cohort_dir))
    assert report["n_breasts_finished"] == 4
    after = {p.name: p.stat().st_mtime_ns for p in cohort_dir.glob("P*.npz")}
    assert set(after) == set(before)
    assert all(after[n] == before[n] for n in after if n != "P0001_R.npz")
    # The breast is regenerated identically (deterministic from seed and index).
    assert np.load(cohort_dir / "P0001_R.npz")["cells"].shape[1] == 4


def test_failed_breast_reported_not_written(tmp_path):
    cfg = _cfg(tmp_path, "n_patients=1", "mesher.tolerance=0", "mesher.max_attempts=1")
    report = run_cohort(cfg)
    assert len(report["failures"]) == 2
    assert "no lattice spacing gave 2250 +- 0 elements" in report["failures"][0]["reason"]
    assert not list(tmp_path.glob("P*.npz"))


def test_mesh_breast_command(tmp_path, ellipsoid_volume):
    """A user's NIfTI with its own label values, meshed through the Hydra config."""
    import nibabel

    from fem.mesh_breast import mesh_breast

    data = ellipsoid_volume.labels.astype(np.int16) * 10  # fat 10, gland 20, muscle 30
    nibabel.save(nibabel.Nifti1Image(data, ellipsoid_volume.affine), str(tmp_path / "case.nii.gz"))
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "mesh_breast",
            overrides=[
                f"input={tmp_path / 'case.nii.gz'}",
                "reader.label_map.fat=10",
                "reader.label_map.gland=[20]",
                "reader.label_map.muscle=30",
                "reader.mesher.target_elements=900",
                "reader.mesher.tolerance=150",
            ],
        )
    stem = mesh_breast(cfg)
    assert stem == tmp_path / "case"
    traj = Trajectory.load(tmp_path / "case.npz")
    assert 750 <= traj.n_cells <= 1050 and set(np.unique(traj.tissue)) == {1, 2, 3}
    assert (tmp_path / "case.vtu").is_file() and (tmp_path / "case.png").is_file()
    # The written mesh is itself a valid input, used as is.
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "mesh_breast",
            overrides=[f"input={tmp_path / 'case.vtu'}", f"output={tmp_path / 'again'}"],
        )
    mesh_breast(cfg)
    np.testing.assert_array_equal(Trajectory.load(tmp_path / "again.npz").cells, traj.cells)
