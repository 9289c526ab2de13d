"""The mesh-aware surrogate: graph samples, batching, the network's invariances, training,
checkpoints and predictions on a remeshed breast."""

import dataclasses

import lightning as L
import numpy as np
import pytest
import torch

from datamodules.graphs import (
    CONDITION_FEATURES,
    NODE_FEATURES,
    PAPER_CONDITIONS,
    STEP_INPUTS,
    Conditions,
    MeshGraphDataModule,
    batch_graphs,
    graph_sample,
)
from fem.breasts.mesh import refine
from fem.contract.quality import mesh_edges
from fem.contract.trajectory import Trajectory
from mammo_net.models import (
    compliance_gain,
    interpolate_steps,
    scaled_into_range,
    step_knots,
)
from mammo_net.module import MeshGraphModule, NetworkModule, SurrogateModule
from mammo_net.predictor import load_surrogate, predict_breast
from tests.conftest import SIMULATION_METADATA, tiny_trajectory


def _traj(lat: str = "R") -> Trajectory:
    return tiny_trajectory(lat, patient=1, site="A", simulation=SIMULATION_METADATA)


def test_mesh_edges_are_each_edge_both_ways():
    edges = mesh_edges(np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))
    pairs = set(map(tuple, edges.T))
    assert len(pairs) == edges.shape[1] == 2 * 9  # 6 + 6 edges, 3 shared
    assert all((b, a) in pairs for a, b in pairs)
    assert (1, 4) in pairs and (3, 4) not in pairs


@pytest.mark.parametrize("step", ["unloaded", "compression"])
def test_graph_sample_shapes_and_targets(step):
    traj = _traj()
    sample, norm = graph_sample(traj, step)
    positions = traj.unloaded if step == "unloaded" else traj.compressed
    t, n = positions.shape[:2]
    assert sample["nodes"].shape == (n, len(NODE_FEATURES))
    assert sample["steps"].shape == (t, len(STEP_INPUTS[step]))
    assert sample["conditions"].shape == (len(CONDITION_FEATURES),)
    np.testing.assert_allclose(norm.invert(sample["targets"]), positions, atol=1e-5)
    # the input coordinates are the step's input geometry, normalised like the targets
    reference = traj.points if step == "unloaded" else traj.reference_shape
    np.testing.assert_allclose(norm.invert(sample["nodes"][:, :3]), reference, atol=1e-5)
    # the paper's conditions: stiffness at the reference (log-ratio 0), friction 0.25, cc
    np.testing.assert_array_equal(sample["conditions"], [0, 0, 0, 0, 0.25, 0, 0])


def test_conditions_read_and_refused():
    traj = _traj()
    assert Conditions.of_metadata(traj.metadata) == PAPER_CONDITIONS
    soft = Conditions({**PAPER_CONDITIONS.young, "fat": 550.0}, 0.25, "mlo", 45.0)
    v = soft.vector()
    assert v[0] == pytest.approx(np.log(0.5)) and v[5] == 1.0 and v[6] == pytest.approx(np.pi / 4)
    with pytest.raises(ValueError, match=r"conditions\.young\.gland must be a positive"):
        Conditions({**PAPER_CONDITIONS.young, "gland": -1.0}, 0.25, "cc")
    with pytest.raises(ValueError, match=r"conditions\.view must be"):
        Conditions(PAPER_CONDITIONS.young, 0.25, "lateral")
    with pytest.raises(ValueError, match=r"no modulus for \['skin'\]"):
        Conditions({"fat": 1.0, "gland": 1.0, "muscle": 1.0}, 0.25, "cc")
    with pytest.raises(ValueError, match=r"P9\.npz: metadata field 'simulation'"):
        Conditions.of_metadata({}, "P9.npz")
    # the moduli are a read-only copy: a caller's dict changed later changes no conditions
    young = dict(PAPER_CONDITIONS.young)
    mine = Conditions(young, 0.25, "cc")
    young["fat"] = 1.0
    assert mine == PAPER_CONDITIONS
    with pytest.raises(TypeError):
        PAPER_CONDITIONS.young["fat"] = 1.0  # type: ignore[index]


def test_batch_offsets_edges_and_refuses_other_step_counts():
    a, _ = graph_sample(_traj("L"), "compression")
    b, _ = graph_sample(_traj("R"), "compression")
    batch = batch_graphs([a, b])
    n = len(a["nodes"])
    assert batch["edges"][:, a["edges"].shape[1] :].min() == n
    assert batch["graph"].tolist() == [0] * n + [1] * len(b["nodes"])
    assert batch["targets"].shape == (3, 2 * n, 3)
    short = {**b, "steps": b["steps"][:2], "node_steps": b["node_steps"][:2]}
    with pytest.raises(ValueError, match="share the step count"):
        batch_graphs([a, short])


def _model(step: str = "compression", **settings) -> MeshGraphModule:
    torch.manual_seed(0)
    return MeshGraphModule(
        step, hidden=16, layers=2, slices=4, heads=2, decoder_hidden=16, **settings
    )


def test_network_is_equivariant_to_node_order_and_batching():
    """Renumbering the nodes renumbers the prediction; a breast predicts the same alone and
    beside another (no leak between the graphs of a batch)."""
    model = _model().eval()
    a, _ = graph_sample(_traj("L"), "compression")
    b, _ = graph_sample(_traj("R"), "compression")
    perm = np.array([3, 0, 4, 2, 1])
    inverse = np.argsort(perm)
    permuted = {
        **a,
        "nodes": a["nodes"][perm],
        "edges": inverse[a["edges"]],
        "node_steps": a["node_steps"][:, perm],
    }
    with torch.no_grad():
        alone = model(batch_graphs([a]))
        renumbered = model(batch_graphs([permuted]))
        together = model(batch_graphs([a, b]))
    torch.testing.assert_close(renumbered, alone[:, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(together[:, :5], alone, atol=1e-5, rtol=1e-5)


def test_model_trains_on_a_tiny_cohort_and_improves(trajectory_folder, tmp_path):
    dm = MeshGraphDataModule(str(trajectory_folder), "compression", batch_size=4)
    dm.prepare_data()
    dm.setup()
    model = _model()
    model.hparams.lr = 0.01
    model.adapt(dm)
    batch = next(iter(dm.train_dataloader()))

    def loss() -> float:
        with torch.no_grad():
            return torch.sqrt(((model(batch) - batch["targets"]) ** 2).mean()).item()

    before = loss()
    trainer = L.Trainer(
        max_epochs=15, logger=False, enable_checkpointing=False, enable_progress_bar=False
    )
    trainer.fit(model, dm)
    assert loss() < 0.5 * before
    assert trainer.callback_metrics["val/rmse_last_step_mean_mm"] > 0
    # the checkpoint rebuilds the network and names it; the Att-BLSTM's loader refuses it
    path = tmp_path / "gnn.ckpt"
    trainer.save_checkpoint(path, weights_only=True)
    again = NetworkModule.from_checkpoint(path)
    assert isinstance(again, MeshGraphModule) and again.schema == dm.schema()
    with torch.no_grad():
        torch.testing.assert_close(again(batch), model.eval()(batch))
    with pytest.raises(ValueError, match="a checkpoint of the network 'mesh_gnn', not a Surr"):
        SurrogateModule.from_checkpoint(path)
    # init_from: a fresh network fine-tunes from those weights; another step or size is refused
    torch.manual_seed(1)
    fresh = MeshGraphModule("compression", hidden=16, layers=2, slices=4, heads=2,
                            decoder_hidden=16)  # fmt: skip
    fresh.start_from(path)
    with torch.no_grad():
        torch.testing.assert_close(fresh.eval()(batch), model.eval()(batch))
    with pytest.raises(ValueError, match=r"gnn\.ckpt: a mesh_gnn of the compression step; init"):
        _model("unloaded").start_from(path)
    with pytest.raises(
        ValueError, match=r"gnn\.ckpt: .*other settings: model\.hidden=16 \(here 8\)"
    ):
        MeshGraphModule("compression", hidden=8, layers=2, slices=4, heads=2,
                        decoder_hidden=16).start_from(path)  # fmt: skip
    with pytest.raises(ValueError, match=r"model\.compliance_scaling=None \(here True\)"):
        _model(compliance_scaling=True).start_from(path)  # the same weights, other outputs
    _model(lr=0.1, train_steps=2).start_from(path)  # the fit's settings may change
    # predictions of a remeshed breast (8x the elements) and of other conditions run
    surrogate = load_surrogate(path, "compression")
    assert surrogate.graph and surrogate.name == "mesh_gnn"
    fine, _ = refine(_traj())
    fine = dataclasses.replace(fine, unloaded=fine.points[None])  # the unloaded shape given
    thickness = 0.5  # mm; the skin spans 1 mm along z
    shapes = predict_breast(fine, None, surrogate, [thickness])
    assert shapes.compressed.shape == (1, 3, fine.n_nodes, 3)
    assert np.isfinite(shapes.compressed).all()
    # a thickness sweep is one batch of graphs: each thickness as when predicted alone
    sweep = predict_breast(fine, None, surrogate, [0.7, thickness])
    np.testing.assert_allclose(sweep.compressed[1], shapes.compressed[0], atol=1e-5)
    assert not np.allclose(sweep.compressed[0], sweep.compressed[1])
    soft = Conditions({**PAPER_CONDITIONS.young, "fat": 500.0}, 0.1, "cc")
    other = predict_breast(fine, None, surrogate, [thickness], soft)
    assert not np.allclose(other.compressed, shapes.compressed)


def test_models_refuse_the_other_data(trajectory_folder):
    graphs = MeshGraphDataModule(str(trajectory_folder), "compression")
    with pytest.raises(ValueError, match="model=att_blstm trains on node sequences"):
        SurrogateModule("compression").adapt(graphs)
    from datamodules.trajectories import TrajectoryDataModule

    rows = TrajectoryDataModule(str(trajectory_folder), "compression")
    with pytest.raises(ValueError, match="model=mesh_gnn trains on whole-breast graphs"):
        _model().adapt(rows)


def test_compliance_gain_is_the_fraction_weighted_inverse_modulus():
    """Two breasts: 3 fat nodes and 1 gland node at half and twice the reference moduli
    (gain 0.5**-0.75 * 2**-0.25 = sqrt 2), and one at the reference materials (gain 1)."""
    nodes = torch.tensor([[1.0, 0], [1, 0], [1, 0], [0, 1], [1, 0], [0, 1]])  # (N, 2): fat, gland
    graph = torch.tensor([0, 0, 0, 0, 1, 1])
    conditions = torch.tensor(
        [[np.log(0.5), np.log(2.0), 5.0], [0.0, 0.0, 5.0]], dtype=torch.float32
    )
    gain = compliance_gain(nodes, graph, conditions, ((0, 0), (1, 1)))
    expected = torch.tensor([2**0.5] * 4 + [1.0] * 2)[:, None]
    torch.testing.assert_close(gain, expected)


def test_compliance_scaling_multiplies_the_decoded_displacement(tmp_path):
    """The same weights with and without the scaling: the displacements differ by the gain,
    and at the paper's materials not at all. On by default for the unloaded state only, and
    off for checkpoints written before the setting existed."""
    plain = _model("unloaded", compliance_scaling=False).eval()
    scaled = _model("unloaded", stiffness_range=False).eval()
    assert scaled.scales_compliance and not _model("compression").scales_compliance
    scaled.load_state_dict(plain.state_dict())
    sample, _ = graph_sample(_traj("L"), "unloaded")
    batch = batch_graphs([sample])
    x = batch["nodes"][:, :3]
    with torch.no_grad():
        torch.testing.assert_close(scaled(batch), plain(batch))  # paper materials: gain 1
        batch["conditions"][:, :2] = torch.log(torch.tensor([0.5, 0.8]))
        gain = compliance_gain(
            batch["nodes"], batch["graph"], batch["conditions"], scaled.net.compliance
        )
        assert (gain > 1).all()
        torch.testing.assert_close(scaled(batch) - x, (plain(batch) - x) * gain)
    hparams = dict(scaled.hparams)
    del hparams["compliance_scaling"], hparams["stiffness_range"]
    path = tmp_path / "before.ckpt"
    checkpoint = {"network": "mesh_gnn", "hyper_parameters": hparams}
    torch.save({**checkpoint, "state_dict": scaled.state_dict()}, path)
    assert not NetworkModule.from_checkpoint(path).scales_compliance


def test_scaled_into_range_shifts_the_moduli_together_then_clamps():
    """Columns 0-1 (fat, gland) in [0, 1] each, column 2 (skin) in [0, 1], column 3 not
    bounded: inside, unchanged; uniformly too soft or too stiff, shifted by one amount (the
    ratio kept); a ratio outside every shift, half-way, then clamped."""
    inf = float("inf")
    bounds = torch.tensor([[0.0, 0.0, 0.0, -inf], [1.0, 1.0, 1.0, inf]])
    conditions = torch.tensor(
        [
            [0.2, 0.9, 0.5, 7.0],  # inside
            [-0.5, 0.1, 2.0, -7.0],  # fat too soft: both up by 0.5; skin clamped
            [1.4, 1.2, -1.0, 0.0],  # both too stiff: both down by 0.4
            [-1.0, 2.0, 0.5, 0.0],  # gland / fat too high for any shift: half-way, clamped
        ]
    )
    seen = scaled_into_range(conditions, bounds, [0, 1])
    expected = torch.tensor(
        [
            [0.2, 0.9, 0.5, 7.0],
            [0.0, 0.6, 1.0, -7.0],
            [1.0, 0.8, 0.0, 0.0],
            [0.0, 1.0, 0.5, 0.0],
        ]
    )
    torch.testing.assert_close(seen, expected)


def test_stiffness_range_extrapolates_by_the_compliance_gain(trajectory_folder):
    """A breast uniformly twice as soft as the softest training breast moves exactly twice as
    far as that one (the network sees the range's edge; the gain doubles), where the same
    weights without the range extrapolate in their inputs; the range is recorded from the
    training breasts, and needs the gain."""
    bounded = _model("unloaded").eval()
    free = _model("unloaded", stiffness_range=False).eval()
    free.load_state_dict({k: v for k, v in bounded.state_dict().items() if "bounds" not in k})
    assert bounded.hparams.stiffness_range and not _model().hparams.stiffness_range
    dm = MeshGraphDataModule(str(trajectory_folder), "unloaded", batch_size=4)
    dm.prepare_data()
    dm.setup()
    bounded.adapt(dm)  # every tiny breast has the paper's materials: a one-point range
    torch.testing.assert_close(bounded.net.condition_bounds[:, :4], torch.zeros(2, 4))
    sample, _ = graph_sample(_traj("L"), "unloaded")
    batch = batch_graphs([sample])
    x = batch["nodes"][:, :3]
    with torch.no_grad():
        edge = bounded(batch) - x
        torch.testing.assert_close(edge, free(batch) - x)  # inside the range: unchanged
        batch["conditions"][:, :2] = float(np.log(0.5))  # fat and gland at half the moduli
        torch.testing.assert_close(bounded(batch) - x, 2 * edge)
        assert not torch.allclose(free(batch) - x, 2 * edge, atol=1e-4)
    with pytest.raises(ValueError, match=r"stiffness_range=true needs .*compliance_scaling"):
        _model("compression", stiffness_range=True)


def test_training_decodes_a_sample_of_the_steps_with_the_last():
    model = _model()
    torch.manual_seed(1)
    steps = model.sampled_steps(70)
    assert len(steps) == 16 and steps[-1] == 69
    assert (steps.diff() > 0).all()
    assert model.sampled_steps(10) is None  # fewer steps than the sample: all
    with pytest.raises(ValueError, match="train_steps must be at least 1"):
        MeshGraphModule("compression", train_steps=0)


def test_knots_decode_evenly_spaced_steps_and_interpolate_the_rest():
    knots = step_knots(70, 20)
    assert len(knots) == 20 and knots[-1] == 69 and knots[0] > 0 and (knots.diff() > 0).all()
    assert torch.equal(step_knots(3, 20), torch.arange(3))
    # a trajectory linear in the step index from its start is reproduced exactly
    start, velocity = torch.randn(5, 3), torch.randn(5, 3)
    exact = start + (torch.arange(70)[:, None, None] + 1.0) * velocity  # (T, N, 3)
    torch.testing.assert_close(interpolate_steps(start, exact[knots], knots, 70), exact)
    # the model's knotted trajectory equals its own decode at the knots, between them a chord
    model = _model().eval()
    sample, _ = graph_sample(_traj("L"), "compression")
    sample = {
        **sample,
        "steps": np.repeat(sample["steps"], 10, axis=0),  # 30 steps
        "node_steps": np.repeat(sample["node_steps"], 10, axis=0),
    }
    batch = batch_graphs([sample])
    model.hparams.knots = 4
    knots = step_knots(30, 4)
    with torch.no_grad():
        knotted = model(batch)
        decoded = model(batch, decoded=knots)
    assert knotted.shape == (30, 5, 3)
    torch.testing.assert_close(knotted[knots], decoded)
    a, b = knots[0].item(), knots[1].item()
    mid = (a + b) // 2
    w = (mid - a) / (b - a)
    torch.testing.assert_close(knotted[mid], (1 - w) * decoded[0] + w * decoded[1])
    with pytest.raises(ValueError, match="knots must be at least 1"):
        MeshGraphModule("compression", knots=0)
