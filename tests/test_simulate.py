"""Both steps on a phantom breast (chest wall, plates of both views, a user's constraints),
and their input errors."""

import numpy as np
import pytest
import skfem
from conftest import assert_exact_derivatives

from fem.breasts.mesh import Mesher
from fem.breasts.phantom import LabelVolume
from fem.contract.quality import signed_volume
from fem.contract.trajectory import NodeFlag, Tissue, Trajectory
from fem.engine.boundary import (
    chest_wall,
    chest_wall_fascia,
    chest_wall_nodes,
    chest_wall_normals,
    plate_schedule,
    wall_areas,
)
from fem.engine.simulation import (
    PAPER_MATERIALS,
    Material,
    Simulation,
    compression,
    element_moduli,
    unloaded_state,
)


@pytest.fixture(scope="module")
def unloaded(breast_mesh):
    return unloaded_state(breast_mesh, n_steps=4)


def rigid_muscle_and_interface(traj):
    """Muscle nodes off the interface, interface nodes, and the chest-wall normals there."""
    interface = traj.flagged(NodeFlag.MUSCLE_INTERFACE)
    muscle = np.setdiff1d(traj.cells[traj.tissue == Tissue.MUSCLE], interface)
    return muscle, interface, chest_wall_normals(traj.points[interface])


def test_unloaded_state_physics(breast_mesh, unloaded):
    assert unloaded.shape == (4, breast_mesh.n_nodes, 3)
    u = unloaded - breast_mesh.points
    muscle, interface, normals = rigid_muscle_and_interface(breast_mesh)
    assert muscle.size and np.abs(u[:, muscle]).max() == 0.0  # the muscle does not deform
    # The interface slides along the chest wall: no motion along its normal, some along it.
    assert np.abs(np.einsum("tij,ij->ti", u[:, interface], normals)).max() < 1e-10
    assert np.linalg.norm(u[-1, interface], axis=1).max() > 0.1
    # Removing the prone (anterior) gravity moves the breast posteriorly, more at each step.
    front = breast_mesh.points[:, 1] > np.percentile(breast_mesh.points[:, 1], 90)
    sag = -u[:, front, 1].mean(axis=1)
    assert np.all(np.diff(sag) > 0) and sag[-1] > 1.0
    # Nearly incompressible: the volume changes by less than 1 %, no element inverts.
    vol = signed_volume(unloaded[-1], breast_mesh.cells)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(
        signed_volume(breast_mesh.points, breast_mesh.cells).sum(), rel=0.01
    )


def test_nodal_averaging_is_softer_than_locking_p1(breast_mesh, unloaded):
    plain = unloaded_state(breast_mesh, n_steps=1, averaging="element")
    sag_nodal = np.linalg.norm(unloaded[-1] - breast_mesh.points, axis=1).max()
    sag_p1 = np.linalg.norm(plain[-1] - breast_mesh.points, axis=1).max()
    assert sag_nodal > 1.05 * sag_p1  # 1.08 with the rigid muscle and sliding interface


def test_tissue_without_material(breast_mesh):
    materials = {k: v for k, v in PAPER_MATERIALS.items() if k != "gland"}
    if not (breast_mesh.tissue == Tissue.GLAND).any():
        pytest.skip("phantom without gland elements")
    with pytest.raises(ValueError, match=r"tissue 'gland' .* has no material parameters"):
        element_moduli(breast_mesh.tissue, materials, "b.vtu")
    mu, kappa = element_moduli(breast_mesh.tissue, {**materials, "gland": Material(2500.0)})
    np.testing.assert_allclose(kappa / mu, 2 * 1.495 / (3 * 0.01))  # K / mu at nu = 0.495


def test_mesh_without_interface_nodes(breast_mesh):
    from dataclasses import replace

    no_muscle = replace(
        breast_mesh, node_flags=breast_mesh.node_flags & ~np.uint8(NodeFlag.MUSCLE_INTERFACE)
    )
    no_muscle.metadata["source"] = "b.vtu"
    with pytest.raises(ValueError, match=r"b\.vtu: no muscle/breast interface nodes"):
        chest_wall(no_muscle, no_muscle.points)


def test_skin_membrane_stiffens_the_breast(breast_mesh, unloaded):
    bare = unloaded_state(
        breast_mesh, {k: v for k, v in PAPER_MATERIALS.items() if k != "skin"}, n_steps=1
    )
    with_skin = np.linalg.norm(unloaded[-1] - breast_mesh.points, axis=1).max()
    assert with_skin < np.linalg.norm(bare[-1] - breast_mesh.points, axis=1).max()


def schedule(traj, start, ratio, view="cc"):
    return plate_schedule(traj, start, view=view, compression_ratio=ratio)


@pytest.fixture(scope="module", params=["cc", "mlo"])
def compressed(request, breast_mesh, unloaded):
    plates = schedule(breast_mesh, unloaded[-1], 0.4, request.param)
    return compression(breast_mesh, unloaded[-1], plates, n_steps=4)


def test_compression_between_plates(breast_mesh, unloaded, compressed):
    """Both views: the plates reach the gap, no covered skin node lies inside a plate along
    its (possibly oblique) normal, nothing inverts, the volume holds, the muscle stays and the
    interface moves only along the chest wall."""
    result = compressed
    assert result.positions.shape == (4, breast_mesh.n_nodes, 3)
    assert result.plates.shape == (4, 2, 3, 3)
    assert np.all(np.diff(result.compression_ratio) > 0)
    assert result.compression_ratio[-1] == pytest.approx(0.4)
    assert_compression_invariants(
        breast_mesh, unloaded[-1], result.positions[-1], result.plates[-1]
    )


def assert_compression_invariants(mesh, start, x, plates):
    """The cohort's invariants of a compressed shape ``x`` (N, 3) from ``start``: no covered
    skin node inside a plate along its (possibly oblique) normal, no inverted element, the
    volume within 3 %, the rigid muscle still and the interface moved only along the chest
    wall."""
    skin = mesh.flagged(NodeFlag.SKIN)
    for origin, normal, axis in plates:
        covered = (x[skin] - origin) @ axis > 1e-9
        assert ((x[skin[covered]] - origin) @ normal).min() > -1e-9
    vol = signed_volume(x, mesh.cells)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(signed_volume(start, mesh.cells).sum(), rel=0.03)
    muscle, interface, _ = rigid_muscle_and_interface(mesh)
    u = x - start
    assert np.abs(u[muscle]).max() == 0.0
    normals = chest_wall_normals(start[interface])
    # exact up to round-off: relative to the largest displacement (a 20k breast: 2.5e-9 mm)
    along = np.abs(np.einsum("ij,ij->i", u[interface], normals)).max()
    assert along < 1e-9 * max(1.0, np.abs(u).max())


def test_compression_thicker_than_breast(breast_mesh, unloaded):
    with pytest.raises(ValueError, match=r"compressed thickness 900\.0 mm is not smaller"):
        plate_schedule(breast_mesh, unloaded[-1], 900.0)


def test_users_own_problem(breast_mesh, tmp_path):
    """No chest wall but a user's file of nodes held along chosen axes, no unloaded step, half
    gravity, two plates moving towards each other, an element set with its own material: the
    held components stay exactly, the set's material is used; bad files name themselves."""
    from dataclasses import replace

    wall = breast_mesh.flagged(NodeFlag.MUSCLE_INTERFACE)
    muscle = np.unique(breast_mesh.cells[breast_mesh.tissue == Tissue.MUSCLE])
    bare = replace(breast_mesh, metadata={**breast_mesh.metadata, "source": "user.vtu"})
    (tmp_path / "held.txt").write_text(
        "".join(f"{i} y\n" for i in wall) + "".join(f"{i}\n" for i in np.setdiff1d(muscle, wall))
    )
    np.savetxt(tmp_path / "stiff.txt", np.flatnonzero(bare.tissue == Tissue.GLAND)[:20], fmt="%d")
    skin = bare.points[bare.flagged(NodeFlag.SKIN)]
    bottom, top = skin[:, 2].min(), skin[:, 2].max()
    edge = float(bare.points[wall, 1].max())
    plate = {"normal": [0, 0, 1], "axis": [0, 1, 0]}
    sim = Simulation(
        materials={
            **PAPER_MATERIALS,
            "stiff": {"mu": 5000.0, "kappa": 5e5, "elements": str(tmp_path / "stiff.txt")},
        },
        unloaded_steps=0,
        compression_steps=3,
        chest_wall="none",
        constraints=str(tmp_path / "held.txt"),
        compression_gravity=[0.0, 0.0, -4.905],
        plates={
            "lower": {**plate, "origin": [0, edge, bottom], "travel": [0, 0, 5.0]},
            "upper": {
                "origin": [0, edge, top],
                "normal": [0, 0, -1],
                "axis": [0, 1, 0],
                "travel": [0, 0, -10.0],
            },
        },
    )
    out = sim(bare)
    assert out.unloaded.shape[0] == 0
    u = out.compressed - bare.points
    assert np.abs(u[:, wall, 1]).max() == 0.0 and np.abs(u[:, wall][..., [0, 2]]).max() > 0.01
    assert out.plates[-1, 1, 0, 2] - out.plates[-1, 0, 0, 2] == pytest.approx(top - bottom - 15)
    meta = out.metadata["simulation"]
    assert meta["materials"]["stiff"]["mu"] == 5000.0 and meta["chest_wall"] == "none"
    (tmp_path / "bad.txt").write_text("0 w\n")
    with pytest.raises(ValueError, match=r"bad\.txt: cannot read held nodes .* line 1"):
        replace(sim, constraints=str(tmp_path / "bad.txt"))(bare)
    with pytest.raises(ValueError, match=r"simulation\.plates: the plates must be parallel"):
        Simulation(
            plates={
                "lower": {**plate, "origin": [0, 0, 0]},
                "upper": {**plate, "origin": [0, 0, 9]},
            }
        )


def test_a_breast_without_muscle_hangs_on_its_posterior_cut(ellipsoid_volume):
    """A segmentation cropped at the chest wall (no muscle label): its flat posterior cut face
    is the chest wall, not skin; both steps run with the cut tied and its rim sliding."""
    labels = np.where(ellipsoid_volume.labels == Tissue.MUSCLE, 0, ellipsoid_volume.labels)
    volume = LabelVolume(labels.astype(np.uint8), ellipsoid_volume.affine, "cropped.nii")
    traj = Mesher(target_elements=1500, tolerance=500)(volume, {"source": "cropped.nii"})
    chest = chest_wall_nodes(traj)
    y = traj.points[:, 1]
    assert chest.size > 20 and np.ptp(y[chest]) < 5.0 and y[chest].min() == y.min()  # ~9 mm edges
    skin_y = traj.points[traj.skin, 1].max(1)  # no skin triangle lies on the cut
    assert skin_y.min() > y.min() + 1e-9
    result = Simulation(unloaded_steps=2, compression_steps=3, compression_ratio=0.3)(traj)
    inner = np.setdiff1d(chest, traj.flagged(NodeFlag.SKIN))
    np.testing.assert_array_equal(result.unloaded[:, inner], np.tile(traj.points[inner], (2, 1, 1)))
    assert result.metadata["simulation"]["compression_ratio"] == pytest.approx(0.3)
    assert result.metadata["simulation"]["min_element_volume_ratio"] > 0


@pytest.mark.parametrize("steps", [(20, 10), pytest.param((70, 35), marks=pytest.mark.slow)])
def test_two_load_paths_end_in_the_same_equilibrium(breast_mesh, unloaded, steps):
    """The equilibrium is unique in practice: compressed to 70 % (friction, skin membrane,
    standing gravity, sliding chest wall) in two numbers of steps, the breast ends within
    0.05 mm RMS (measured with the fascia 0.003 mm for 20/10 and 0.024 mm for 70/35 steps;
    free sliding: 0.037 and 0.022 mm)."""
    plates = schedule(breast_mesh, unloaded[-1], 0.7)
    a, b = (compression(breast_mesh, unloaded[-1], plates, n_steps=n).positions[-1] for n in steps)
    assert np.sqrt((np.linalg.norm(a - b, axis=1) ** 2).mean()) < 0.05


def test_mlo_view_end_to_end(breast_mesh, tmp_path):
    """Simulation(view="mlo"): the plates turned 45 degrees about y towards the medial side
    (a left breast: +x), recorded as frames, saved and read back, and the learning features
    computed in the plates' frame."""
    from datamodules.features import compression_features
    from fem.contract.trajectory import Trajectory

    sim = Simulation(view="mlo", unloaded_steps=2, compression_steps=3, compression_ratio=0.4)
    out = sim(breast_mesh)
    lower = out.plates[0, 0]
    np.testing.assert_allclose(lower[1], [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(out.plates[:, 1, 1], np.tile(-lower[1], (3, 1)))
    assert out.compression_ratio[-1] == pytest.approx(0.4)
    assert out.metadata["simulation"]["view"] == "mlo"
    back = Trajectory.load(out.save(tmp_path / "mlo.npz"))
    features, targets, norm = compression_features(back)
    assert features.shape == (3, back.n_nodes, 22) and np.isfinite(features).all()
    np.testing.assert_allclose(norm.invert(targets), back.compressed, atol=1e-3)


def test_simulation_failed_crosses_process_pools():
    import pickle

    from fem.engine.simulation import SimulationFailed

    error = pickle.loads(pickle.dumps(SimulationFailed("b.npz", "compression", "why", {"a": 1.0})))
    assert str(error) == "b.npz: compression failed: why" and error.seconds == {"a": 1.0}


@pytest.mark.slow
def test_real_size_breast_through_both_steps(phantom):
    """A breast meshed at about 20,000 tetrahedra (9x the paper's) through both steps keeps the
    cohort's invariants (the solver by size: `fem.engine.linear`)."""
    volume, meta = phantom
    mesh = Mesher(target_elements=20000, tolerance=2500)(volume, meta)
    assert 17500 <= mesh.n_cells <= 22500
    out = Simulation(unloaded_steps=10, compression_steps=10)(mesh)
    assert out.compression_ratio[-1] == pytest.approx(meta["target_compression_ratio"])
    assert_compression_invariants(mesh, out.unloaded[-1], out.compressed[-1], out.plates[-1])


def walled_block(length: float = 30.0, width: float = 40.0) -> Trajectory:
    """A fat block (y in [0, length]) on a 5 mm muscle slab (y in [-5, 0]), without skin: the
    muscle/breast interface, y = 0, is a flat chest wall of ``width`` x ``width`` mm^2."""
    edges = np.linspace(-width / 2, width / 2, 5)
    m = skfem.MeshTet.init_tensor(edges, np.linspace(-5, length, 8), edges)
    p, t = m.p.T.copy(), m.t.T.copy()
    neg = signed_volume(p, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    muscle = p[t, 1].mean(axis=1) < 0
    flags = np.where(np.isclose(p[:, 1], 0), NodeFlag.MUSCLE_INTERFACE, 0).astype(np.uint8)
    return Trajectory(
        p,
        t.astype(np.int64),
        np.where(muscle, Tissue.MUSCLE, Tissue.FAT).astype(np.uint8),
        np.full(len(p), 2, np.uint8),
        flags,
        np.zeros((0, 3), np.int64),
        metadata={"source": "walled block"},
    )


def test_fascia_holds_a_block_on_the_sliding_wall_by_its_stiffness():
    """A stiff block pulled along a sliding chest wall by a body force g (Pa/mm) slides as a
    whole by g V / (k A): the fascia's stiffness k per unit area times the wall's area A. The
    muscle is made so soft that its elements do not resist; half the slab's weight (lumped
    on its nodes) lies on the wall, so V is the block's volume plus half the slab's."""
    traj = walled_block()
    materials = {"fat": Material(young=1e6, poisson=0.45), "muscle": Material(young=1e-3)}
    k, g, volume, area = 75.0, 2.5, 40.0 * (30.0 + 5.0 / 2) * 40.0, 40.0 * 40.0
    x = unloaded_state(traj, materials, n_steps=1, body_force=(0.0, 0.0, -g), fascia=k)[-1]
    slide = (x - traj.points)[traj.points[:, 1] >= 0, 2]
    assert slide.mean() == pytest.approx(-g * volume / (k * area), rel=0.01)  # 1.08 mm
    assert np.ptp(slide) < 0.05 * abs(slide.mean())  # nearly rigidly (2 % shear)
    free = unloaded_state(traj, materials, n_steps=1, body_force=(0.0, 0.0, -g), fascia=0.0)[-1]
    assert np.abs(free - traj.points)[:, 2].max() > 10 * abs(slide.mean())  # only the muscle


def test_fascia_is_a_tangential_spring(breast_mesh):
    """The fascia's force is its energy's gradient and its tangent the force's Jacobian; it
    acts only along the wall, on its sliding nodes, with the wall's area."""
    fascia = chest_wall_fascia(breast_mesh, breast_mesh.points, "sliding", 75.0)
    assert chest_wall_fascia(breast_mesh, breast_mesh.points, "tied") is None
    x = breast_mesh.points + np.random.default_rng(1).normal(0, 1.0, breast_mesh.points.shape)
    assert_exact_derivatives(fascia, x)
    f = fascia.internal_force(x).reshape(-1, 3)[fascia.nodes]
    assert np.abs((f * fascia.normals).sum(axis=1)).max() < 1e-9 * np.abs(f).max()
    area = wall_areas(breast_mesh, breast_mesh.points)
    assert fascia.stiffness.sum() == pytest.approx(75.0 * area[fascia.nodes].sum())
    assert 1e3 < area.sum() < 1e5  # mm^2: a chest wall of a breast
