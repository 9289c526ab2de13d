import meshio
import numpy as np
import pytest

from fem.contract.plates import cc_plates
from fem.contract.timeseries import write_time_series
from fem.contract.trajectory import Trajectory


def _tiny(t1: int, t2: int) -> Trajectory:
    """Two tetrahedra sharing a face, with synthetic (translated, squeezed) trajectories."""
    points = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10]], float)
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    rng = np.random.default_rng(0)
    sag = -0.5 * np.arange(1, t1 + 1)[:, None, None] * [0, 0, 1]
    unloaded = points + sag  # (T1, 5, 3): sagging under gravity
    squeeze = 1 - 0.1 * np.arange(1, t2 + 1)[:, None, None] * [0, 0, 1]
    compressed = points * squeeze + rng.normal(0, 0.1, (t2, 5, 3))  # (T2, 5, 3)
    return Trajectory(
        points=points,
        cells=cells,
        tissue=np.array([1, 2], np.uint8),
        node_tissue_code=np.array([2, 6, 6, 6, 4], np.uint8),
        node_flags=np.array([1, 3, 17, 5, 8], np.uint8),
        skin=np.array([[0, 1, 2]]),
        unloaded=unloaded,
        compressed=compressed,
        plates=cc_plates(np.zeros((t2, 2)), np.ones((t2, 2))),
        compression_ratio=np.linspace(0.1, 0.1 * t2, t2),
    )


@pytest.mark.parametrize(("t1", "t2"), [(3, 4), (2, 0), (0, 0)])
def test_time_series_round_trip(tmp_path, t1, t2):
    traj = _tiny(t1, t2)
    path = tmp_path / "out" / "breast.xdmf"
    assert write_time_series(traj, path) == path
    assert [p.name for p in path.parent.iterdir()] == ["breast.xdmf"]  # no temp, no side file

    expected = [traj.points, *traj.unloaded, *traj.compressed]
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        np.testing.assert_array_equal(points, traj.points)
        np.testing.assert_array_equal(cells[0].data, traj.cells)
        assert cells[0].type == "tetra"
        assert reader.num_steps == 1 + t1 + t2
        for k in range(reader.num_steps):
            t, point_data, cell_data = reader.read_data(k)
            assert t == k
            np.testing.assert_allclose(
                point_data["displacement"], expected[k] - traj.points, rtol=0, atol=1e-12
            )
            np.testing.assert_array_equal(point_data["node_flags"], traj.node_flags)
            np.testing.assert_array_equal(point_data["tissue_code"], traj.node_tissue_code)
            np.testing.assert_array_equal(cell_data["tissue"][0], traj.tissue)
    text = path.read_text()
    assert 'Name="reference_0"' in text
    assert text.count("<Geometry") == 1  # the mesh lives in step 0 only: one block in ParaView
    assert 'Name="mesh"' not in text
    assert text.count('Value="compression"') == t2
