"""An FE trajectory as an XDMF time series, to scrub through both simulation steps in ParaView.

The file is a single self-contained XDMF 3 document (data inline as XML text, no HDF5 side
file), written with `meshio.xdmf.TimeSeriesWriter`. Open it in ParaView with the "Xdmf3
Reader" and apply "Warp By Vector" on ``displacement`` to see the deformed breast.
"""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree as ET

import meshio
import numpy as np
from numpy.typing import NDArray

from fem.contract.atomic import atomic_path
from fem.contract.trajectory import Trajectory


def time_steps(traj: Trajectory) -> list[tuple[str, int, NDArray[np.float64]]]:
    """The steps of the time series in order: reference, unloaded-state, compression.

    Parameters
    ----------
    traj : Trajectory
        Mesh and (possibly empty) trajectories.

    Returns
    -------
    list of (kind, index, positions)
        ``kind`` is ``"reference"``, ``"unloaded"`` or ``"compression"``; ``index`` counts
        from 0 within the kind; ``positions`` is the (N, 3) node positions in mm. Entry
        ``k`` of the list is time step ``k``: 0 is the reference geometry, 1..T1 the
        unloaded-state step, T1+1..T1+T2 the compression step.
    """
    steps: list[tuple[str, int, NDArray[np.float64]]] = [("reference", 0, traj.points)]
    steps += [("unloaded", i, x) for i, x in enumerate(traj.unloaded)]
    steps += [("compression", i, x) for i, x in enumerate(traj.compressed)]
    return steps


def _mesh_into_first_step(writer: meshio.xdmf.TimeSeriesWriter) -> None:
    """Move the mesh (topology, geometry) from its own grid into the first time step.

    meshio writes the mesh as a separate grid beside the temporal collection, which ParaView
    shows as a second, static block over the moving one; here the first step holds the mesh
    itself and the later steps keep pointing at it (by its name, ``writer.mesh_name``).
    """
    mesh = next(g for g in writer.domain if g.get("Name") == writer.mesh_name)
    first = writer.collection[0]
    for child in list(first):
        if child.tag.endswith("include"):
            first.remove(child)
    for i, child in enumerate(c for c in mesh if c.tag in ("Topology", "Geometry")):
        first.insert(i, child)
    first.set("GridType", "Uniform")
    writer.domain.remove(mesh)


def write_time_series(traj: Trajectory, path: str | Path) -> Path:
    """Write the reference mesh and every recorded step as an XDMF time series, atomically.

    Parameters
    ----------
    traj : Trajectory
        Mesh with points (N, 3) mm, cells (E, 4), tissue (E,), node_flags (N,),
        node_tissue_code (N,), and the recorded node positions ``unloaded`` (T1, N, 3) mm
        and ``compressed`` (T2, N, 3) mm (either may be empty).
    path : str or Path
        Output file, conventionally ``*.xdmf``. It is written under a temporary name and
        renamed when complete.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    The file holds 1 + T1 + T2 time steps; the time value of step ``k`` is ``k`` (a step
    index, not seconds). Each step carries

    * point data ``displacement`` (N, 3) float64, mm: positions minus ``traj.points``
      (zero at step 0);
    * point data ``node_flags`` and ``tissue_code`` (N,) int32, constant over time;
    * cell data ``tissue`` (E,) int32, constant over time.

    Each step's grid is named ``"<kind>_<index>"`` (kind ``reference``, ``unloaded`` or
    ``compression``) and carries XDMF ``Information`` elements ``step_kind`` and, for
    compression steps, ``compression_ratio``.
    """
    path = Path(path)
    reference = np.asarray(traj.points, np.float64)
    cells = [("tetra", np.asarray(traj.cells, np.int64))]
    point_constant = {
        "node_flags": np.asarray(traj.node_flags, np.int32),
        "tissue_code": np.asarray(traj.node_tissue_code, np.int32),
    }
    cell_data = {"tissue": [np.asarray(traj.tissue, np.int32)]}
    with atomic_path(path) as tmp:
        with meshio.xdmf.TimeSeriesWriter(tmp, data_format="XML") as writer:
            writer.mesh_name = "reference_0"
            writer.write_points_cells(reference, cells)
            for k, (kind, index, positions) in enumerate(time_steps(traj)):
                displacement = np.asarray(positions, np.float64) - reference
                writer.write_data(
                    float(k),
                    point_data={"displacement": displacement, **point_constant},
                    cell_data=cell_data,
                )
                grid = writer.collection[-1]
                grid.set("Name", f"{kind}_{index}")
                ET.SubElement(grid, "Information", Name="step_kind", Value=kind)
                if kind == "compression":
                    ratio = float(traj.compression_ratio[index])
                    ET.SubElement(grid, "Information", Name="compression_ratio", Value=f"{ratio}")
            _mesh_into_first_step(writer)
    return path
