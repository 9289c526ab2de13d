import numpy as np
import pytest
import skfem

from fem.breasts.mesh import Mesher, bcc_lattice, refine
from fem.breasts.phantom import PhantomGenerator
from fem.contract.quality import boundary_faces, dihedral_angles, radius_ratio, signed_volume
from fem.contract.trajectory import TISSUE_BIT, NodeFlag, Tissue


def test_bcc_lattice_congruent_positive():
    points, cells = bcc_lattice(np.zeros(3), np.full(3, 3.0), 1.0)
    vol = signed_volume(points, cells)
    np.testing.assert_allclose(vol, 1 / 12)
    dih = np.sort(np.round(dihedral_angles(points, cells), 6), axis=1)
    np.testing.assert_allclose(dih, np.tile([60, 60, 60, 60, 90, 90], (len(cells), 1)), atol=1e-6)
    # Interior of the box is tiled: 12 tetrahedra per cube except the missing half-cells at the rim.
    assert vol.sum() == pytest.approx(27 - 6 * 9 * (1 / 12) * 2, rel=1e-12)


def test_quality_of_regular_tetrahedron():
    p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    t = np.array([[0, 1, 2, 3]])
    if signed_volume(p, t)[0] < 0:
        t = t[:, [0, 2, 1, 3]]
    assert radius_ratio(p, t)[0] == pytest.approx(1.0)
    np.testing.assert_allclose(dihedral_angles(p, t), np.degrees(np.arccos(1 / 3)))
    assert radius_ratio(p, t[:, [0, 2, 1, 3]])[0] == pytest.approx(-1.0)


def test_element_count_window_and_quality(breast_mesh):
    m = breast_mesh.metadata["mesh"]
    assert 2000 <= breast_mesh.n_cells <= 2500
    assert m["quality"]["n_inverted"] == 0
    assert radius_ratio(breast_mesh.points, breast_mesh.cells).min() >= 0.2 - 1e-9


def test_mesh_volume_matches_voxels(breast_mesh, phantom):
    volume, _ = phantom
    voxel = float((volume.labels != 0).sum()) * volume.voxel_volume
    mesh = skfem.MeshTet(breast_mesh.points.T, breast_mesh.cells.T)
    basis = skfem.Basis(mesh, skfem.ElementTetP1())
    one = skfem.Functional(lambda w: 1.0 + 0 * w.x[0])
    assert one.assemble(basis) == pytest.approx(voxel, rel=0.05)
    assert signed_volume(breast_mesh.points, breast_mesh.cells).sum() == pytest.approx(
        one.assemble(basis)
    )


def test_node_codes_consistent_with_elements(breast_mesh):
    code = np.zeros(breast_mesh.n_nodes, np.uint8)
    for cell, t in zip(breast_mesh.cells, breast_mesh.tissue, strict=True):
        code[cell] |= TISSUE_BIT[Tissue(t)]
    np.testing.assert_array_equal(code, breast_mesh.node_tissue_code)
    assert set(np.unique(code)) <= set(range(1, 8))
    assert {1, 2}.issubset(set(breast_mesh.tissue.tolist()) | {1}) and 3 in breast_mesh.tissue


def test_node_flags(breast_mesh):
    flags = breast_mesh.node_flags
    skin = breast_mesh.flagged(NodeFlag.SKIN)
    np.testing.assert_array_equal(np.unique(breast_mesh.skin), skin)
    interface = breast_mesh.flagged(NodeFlag.MUSCLE_INTERFACE)
    code = breast_mesh.node_tissue_code[interface]
    assert interface.size > 0 and np.all(code & 1) and np.all(code & 6)
    upper = breast_mesh.flagged(NodeFlag.UPPER_CONTACT)
    lower = breast_mesh.flagged(NodeFlag.LOWER_CONTACT)
    assert np.all(flags[upper] & NodeFlag.SKIN) and np.intersect1d(upper, lower).size == 0
    # The upper-contact nodes are the cranial part of the skin.
    assert breast_mesh.points[upper, 2].mean() > breast_mesh.points[lower, 2].mean()


def test_skin_is_closed_outward_surface_of_breast(breast_mesh):
    faces, owner = boundary_faces(breast_mesh.points, breast_mesh.cells)
    # Divergence theorem: the outward boundary encloses the mesh volume.
    p = breast_mesh.points[faces]
    enclosed = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6
    assert enclosed == pytest.approx(signed_volume(breast_mesh.points, breast_mesh.cells).sum())
    assert len(breast_mesh.skin) == (breast_mesh.tissue[owner] != Tissue.MUSCLE).sum()


def test_determinism(breast_mesh):
    """Same seed -> identical mesh arrays, from a fresh generator and mesher."""
    volume, meta = PhantomGenerator(seed=7).breast(1, "L")
    again = Mesher()(volume, meta)
    for name in ("points", "cells", "tissue", "node_tissue_code", "node_flags", "skin"):
        np.testing.assert_array_equal(getattr(again, name), getattr(breast_mesh, name))


def test_target_elements_configurable(ellipsoid_volume):
    mesh = Mesher(target_elements=800, tolerance=100)(ellipsoid_volume)
    assert 700 <= mesh.n_cells <= 900
    voxel = float((ellipsoid_volume.labels != 0).sum())
    assert signed_volume(mesh.points, mesh.cells).sum() == pytest.approx(voxel, rel=0.05)
    assert set(np.unique(mesh.tissue)) == {1, 2, 3}


def test_volume_without_breast_labels(ellipsoid_volume):
    from fem.breasts.phantom import LabelVolume

    only_muscle = LabelVolume(
        np.where(ellipsoid_volume.labels == 3, 3, 0).astype(np.uint8),
        ellipsoid_volume.affine,
        "m.nii",
    )
    with pytest.raises(ValueError, match=r"m\.nii: no breast labels"):
        Mesher()(only_muscle)


@pytest.mark.slow
def test_many_breasts_meet_mesh_contract():
    """40 breasts of another seed: element window, quality floor, volume, tissue codes."""
    gen, mesher = PhantomGenerator(seed=11), Mesher()
    for patient in range(20):
        for lat in "LR":
            volume, meta = gen.breast(patient, lat)
            mesh = mesher(volume, meta)
            info = mesh.metadata["mesh"]
            assert 2000 <= mesh.n_cells <= 2500
            assert radius_ratio(mesh.points, mesh.cells).min() >= 0.2 - 1e-9
            assert abs(info["volume_error"]) < 0.05
            assert mesh.flagged(NodeFlag.MUSCLE_INTERFACE).size > 0
            assert mesh.flagged(NodeFlag.UPPER_CONTACT).size > 0


def test_refine_keeps_geometry_tissue_and_the_coarse_nodes(breast_mesh):
    """Nested refinement (`refine`): eight children per element in their parent, the coarse
    nodes first and unmoved, the same volume per tissue, the interface and skin kept."""
    fine, parent = refine(breast_mesh, 1)
    n = breast_mesh.n_nodes
    assert fine.n_cells == 8 * breast_mesh.n_cells
    np.testing.assert_array_equal(fine.points[:n], breast_mesh.points)
    assert np.all(np.bincount(parent, minlength=breast_mesh.n_cells) == 8)
    assert signed_volume(fine.points, fine.cells).min() > 0
    for tissue in (Tissue.FAT, Tissue.GLAND, Tissue.MUSCLE):
        coarse_v = signed_volume(breast_mesh.points, breast_mesh.cells)[
            breast_mesh.tissue == tissue
        ]
        fine_v = signed_volume(fine.points, fine.cells)[fine.tissue == tissue]
        assert fine_v.sum() == pytest.approx(coarse_v.sum(), rel=1e-12)
    for flag in (NodeFlag.MUSCLE_INTERFACE, NodeFlag.SKIN):
        coarse = breast_mesh.flagged(flag)
        assert np.array_equal(fine.flagged(flag)[: len(coarse)], coarse)
    assert len(fine.skin) == 4 * len(breast_mesh.skin)
