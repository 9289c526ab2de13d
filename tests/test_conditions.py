"""Cohort v2: per-breast simulation conditions (`fem.breasts.conditions.ConditionSampler`),
their draws, their settings and the cohort's simulation stage with them."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from test_cohort import CONF, _cfg

from fem import cohort as cohort_command
from fem.breasts.cohort_simulation import simulate_cohort, trajectory_folder, varied
from fem.breasts.conditions import SAMPLED_MATERIALS, ConditionSampler
from fem.breasts.mesh import Mesher
from fem.cohort import check_settings, run_cohort
from fem.contract.trajectory import Trajectory
from fem.engine.simulation import PAPER_MATERIALS, Simulation

WIDE = dict(
    young={
        "fat": (550.0, 3300.0),
        "gland": (1250.0, 7500.0),
        "muscle": (3000.0, 18000.0),
        "skin": (500.0, 3000.0),
    },
    friction=(0.1, 0.5),
    views=("cc", "mlo"),
    angle=(40.0, 60.0),
    compression_ratio_factor=(0.8, 1.2),
    compression_ratio_range=(0.05, 0.775),
    seed=3,
)
NAMES = [f"P{p:04d}_{lat}" for p in range(100) for lat in "LR"]


def test_the_draws_are_a_function_of_seed_name_and_view():
    sampler = ConditionSampler(**WIDE)
    again = ConditionSampler(**WIDE)
    assert sampler.sample("P0007_L", 0.4, "mlo") == again.sample("P0007_L", 0.4, "mlo")
    assert sampler.sample("P0007_L", 0.4) == sampler.sample("P0007_L", 0.4, "cc")  # first view
    cc, mlo = sampler.sample("P0007_L", 0.4, "cc"), sampler.sample("P0007_L", 0.4, "mlo")
    # the breast's tissue and skin are the same in both views; the plates are drawn per view
    assert cc["materials"] == mlo["materials"] and cc["friction"] == mlo["friction"]
    assert cc["compression_ratio"] != mlo["compression_ratio"]
    assert (cc["view"], mlo["view"]) == ("cc", "mlo") and "angle" not in cc
    other = sampler.sample("P0007_R", 0.4, "cc")
    assert other["materials"]["fat"]["young"] != cc["materials"]["fat"]["young"]
    assert other["friction"] != cc["friction"]
    reseeded = ConditionSampler(**{**WIDE, "seed": 4}).sample("P0007_L", 0.4, "cc")
    assert reseeded["friction"] != cc["friction"]
    # a material left out keeps the simulation's, and the others' draws do not move
    young = {k: v for k, v in WIDE["young"].items() if k != "muscle"}
    fewer = ConditionSampler(**{**WIDE, "young": young}).sample("P0007_L", 0.4, "cc")
    assert "muscle" not in fewer["materials"]
    assert fewer["materials"]["skin"] == cc["materials"]["skin"]
    assert fewer["friction"] == cc["friction"]


def test_the_draws_lie_in_their_ranges_and_spread_over_them():
    sampler = ConditionSampler(**WIDE)
    draws = [sampler.sample(n, 0.7, view) for n in NAMES for view in ("cc", "mlo")]
    for name in SAMPLED_MATERIALS:
        low, high = WIDE["young"][name]
        e = np.array([d["materials"][name]["young"] for d in draws])
        assert low <= e.min() and e.max() <= high
        # log-uniform: the geometric midpoint splits the draws in half
        assert 0.4 < np.mean(e < np.sqrt(low * high)) < 0.6
        assert all(d["materials"][name]["poisson"] == 0.495 for d in draws)
    assert all(d["materials"]["skin"]["membrane"] == 2.0 for d in draws)
    assert "membrane" not in draws[0]["materials"]["fat"]
    friction = np.array([d["friction"] for d in draws])
    assert 0.1 <= friction.min() and friction.max() <= 0.5 and np.ptp(friction) > 0.3
    angle = np.array([d["angle"] for d in draws if d["view"] == "mlo"])
    assert 40 <= angle.min() and angle.max() <= 60 and np.ptp(angle) > 15
    factor = np.array([d["compression_ratio_factor"] for d in draws])
    assert 0.8 <= factor.min() and factor.max() <= 1.2
    ratio = np.array([d["compression_ratio"] for d in draws])
    np.testing.assert_allclose(ratio, np.clip(0.7 * factor, 0.05, 0.775))
    assert ratio.max() == 0.775 and ratio.min() < 0.6  # clipped above, spread below


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (
            {"young": {"fat": (0.0, 10.0)}},
            r"variation\.young\.fat must be \[low, high\] with 0 < low <= high",
        ),
        ({"young": {"gland": (3000.0, 2000.0)}}, r"variation\.young\.gland must be \[low, high\]"),
        ({"young": {"fat": (1.0, 2.0, 3.0)}}, r"variation\.young\.fat must be \[low, high\]"),
        ({"young": {"fat": "1-2"}}, r"variation\.young\.fat must be \[low, high\]"),
        ({"young": {"tumour": (1.0, 2.0)}}, r"variation\.young\.tumour: not a material"),
        ({"young": [1.0, 2.0]}, r"variation\.young must map materials"),
        ({"friction": (-0.1, 0.2)}, r"variation\.friction must be \[low, high\] with 0 <= low"),
        ({"friction": (0.1, float("nan"))}, r"variation\.friction must be \[low, high\]"),
        ({"views": ["cc", "ap"]}, r"variation\.views must be distinct views"),
        ({"views": ["cc", "cc"]}, r"variation\.views must be distinct views"),
        ({"views": []}, r"variation\.views must be a non-empty list"),
        ({"views": "cc"}, r"variation\.views must be a non-empty list"),
        (
            {"angle": (0.0, 45.0)},
            r"variation\.angle must be \[low, high\] with 0 < low <= high < 90",
        ),
        ({"compression_ratio_factor": (0.0, 1.2)}, r"variation\.compression_ratio_factor must"),
        ({"compression_ratio_range": (0.1, 1.0)}, r"variation\.compression_ratio_range must"),
        ({"poisson": 0.5}, r"variation\.poisson must lie in \[0, 0\.5\)"),
        ({"skin_membrane": 0.0}, r"variation\.skin_membrane must be > 0 mm"),
        ({"seed": -1}, r"variation\.seed must be an integer >= 0"),
        ({"seed": 1.5}, r"variation\.seed must be an integer >= 0"),
    ],
)
def test_bad_settings_are_refused_naming_the_setting(settings, message):
    with pytest.raises(ValueError, match=message):
        ConditionSampler(**settings)


def test_bad_uses_are_refused():
    sampler = ConditionSampler(views=["mlo"])
    with pytest.raises(ValueError, match=r"view 'cc' is not among variation\.views"):
        sampler.sample("P0000_L", 0.4, "cc")
    with pytest.raises(ValueError, match=r"P0000_L: target compression ratio must lie in"):
        sampler.sample("P0000_L", 1.2)
    with_plates = Simulation()
    with_plates.plates = {"lower": {}, "upper": {}}  # only `check` reads it
    with pytest.raises(ValueError, match=r"variation: simulation\.plates must be null"):
        sampler.check(with_plates)
    solid_skin = Simulation(
        materials={**PAPER_MATERIALS, "skin": {"young": 1e3, "elements": "s.txt"}}
    )
    with pytest.raises(
        ValueError, match=r"variation\.young\.skin: simulation\.materials\.skin is a solid"
    ):
        ConditionSampler(young={"skin": (500.0, 3000.0)}).check(solid_skin)


def test_the_config_group_builds_the_sampler_and_null_is_the_paper_cohort(tmp_path):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        paper = compose("cohort")
        v2 = compose("cohort", overrides=["variation=v2", "variation.seed=5"])
        named = compose("cohort_v2")
    assert paper.variation is None  # null: every breast with conf/simulation's conditions
    sampler = instantiate(v2.variation)
    assert isinstance(sampler, ConditionSampler) and sampler.seed == 5
    assert sampler.views == ("cc", "mlo") and set(sampler.young) == set(SAMPLED_MATERIALS)
    assert named.n_patients == 258 and named.out_dir == "data/cohort/v2"
    assert instantiate(named.variation) == replace(sampler, seed=0)


def test_a_cohort_folder_records_its_variation_and_refuses_another(tmp_path):
    folder = tmp_path / "cohort"
    folder.mkdir()
    check_settings(folder, _cfg(folder, "simulate=true"))  # the paper cohort: null recorded
    record = folder / "cohort_config.json"
    stored = json.loads(record.read_text())
    assert stored["variation"] is None
    del stored["variation"]  # a folder recorded before the setting existed: the paper cohort
    record.write_text(json.dumps(stored))
    check_settings(folder, _cfg(folder, "simulate=true"))
    with pytest.raises(ValueError, match=r"variation: None there, \(none\) now"):
        check_settings(folder, _cfg(folder, "simulate=true", "variation=v2"))
    v2 = tmp_path / "v2"
    v2.mkdir()
    check_settings(v2, _cfg(v2, "simulate=true", "variation=v2"))
    check_settings(v2, _cfg(v2, "simulate=true", "variation=v2"))  # resumes
    with pytest.raises(
        ValueError, match=r"variation\.friction: \[0\.1, 0\.5\] there, \[0\.2, 0\.3\] now"
    ):
        check_settings(
            v2, _cfg(v2, "simulate=true", "variation=v2", "variation.friction=[0.2,0.3]")
        )


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "variation.young.fat=[0,1000]",
            r"variation\.young\.fat must be \[low, high\] with 0 < low",
        ),
        (
            "variation.views=[cc,ap]",
            r"variation\.views must be distinct views among \('cc', 'mlo'\)",
        ),
        ("variation.seed=-1", r"variation\.seed must be an integer >= 0"),
    ],
)
def test_the_cohort_refuses_a_bad_variation_before_creating_its_folder(
    tmp_path, monkeypatch, override, message
):
    monkeypatch.setattr(cohort_command, "cohort_executor", lambda *_: pytest.fail("cohort built"))
    cfg = _cfg(tmp_path / "cohort", "simulate=true", "variation=v2", override)
    with pytest.raises(InstantiationException, match=message):
        run_cohort(cfg)
    assert not (tmp_path / "cohort").exists()


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory, phantom):
    """One small meshed breast (about 400 tetrahedra) as a cohort's mesh folder."""
    volume, meta = phantom
    folder = tmp_path_factory.mktemp("meshes")
    Mesher(target_elements=400, tolerance=100)(volume, meta).save(folder / "P0001_L.npz")
    return folder


FEW_STEPS = Simulation(unloaded_steps=2, compression_steps=3)


def test_each_breast_is_simulated_with_its_drawn_conditions_in_each_view(mesh_dir):
    narrow = ConditionSampler(
        young={"fat": (1000.0, 1300.0), "gland": (2000.0, 3000.0), "skin": (900.0, 1100.0)},
        friction=(0.2, 0.3),
        views=("cc", "mlo"),
        angle=(44.0, 50.0),
        compression_ratio_factor=(0.8, 0.9),
        seed=1,
    )
    with ThreadPoolExecutor(1) as pool:
        report = simulate_cohort(pool, mesh_dir, ["P0001_L"], FEW_STEPS, variation=narrow)
    assert set(report["by_view"]) == {"cc", "mlo"}
    assert all(r["n_converged"] == r["reached_target"] == 1 for r in report["by_view"].values())
    target = Trajectory.load(mesh_dir / "P0001_L.npz").metadata["target_compression_ratio"]
    for i, view in enumerate(("cc", "mlo")):
        folder = trajectory_folder(mesh_dir, i, view)
        assert folder.name == ("trajectories" if view == "cc" else "trajectories_mlo")
        traj = Trajectory.load(folder / "P0001_L.npz")
        draw = narrow.sample("P0001_L", target, view)
        sim = traj.metadata["simulation"]
        assert sim["materials"] == {**_recorded(PAPER_MATERIALS), **draw["materials"]}
        assert sim["materials"]["muscle"]["young"] == 6000.0  # not sampled: the simulation's
        assert sim["friction"] == draw["friction"] and sim["view"] == view
        assert sim["angle"] == draw.get("angle", FEW_STEPS.angle)
        assert sim["compression_ratio"] == pytest.approx(draw["compression_ratio"])
        assert traj.compression_ratio[-1] == pytest.approx(0.8 * target, abs=0.1 * target)
        assert traj.metadata["variation"] == {
            "seed": 1,
            "view": view,
            "compression_ratio_factor": draw["compression_ratio_factor"],
            "target_compression_ratio": draw["compression_ratio"],
        }
    # resumable: a finished breast is not simulated again
    stamps = {p: p.stat().st_mtime_ns for p in mesh_dir.glob("trajectories*/P0001_L.npz")}
    with ThreadPoolExecutor(1) as pool:
        simulate_cohort(pool, mesh_dir, ["P0001_L"], FEW_STEPS, variation=narrow)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps and len(stamps) == 2


def test_without_a_variation_the_simulation_is_untouched(mesh_dir, tmp_path):
    (tmp_path / "P0001_L.npz").write_bytes((mesh_dir / "P0001_L.npz").read_bytes())
    with ThreadPoolExecutor(1) as pool:
        report = simulate_cohort(pool, tmp_path, ["P0001_L"], FEW_STEPS)
    assert report["n_converged"] == 1 and "by_view" not in report
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["trajectories"]
    traj = Trajectory.load(tmp_path / "trajectories" / "P0001_L.npz")
    assert "variation" not in traj.metadata
    assert traj.metadata["simulation"]["materials"] == _recorded(PAPER_MATERIALS)
    direct = FEW_STEPS(Trajectory.load(tmp_path / "P0001_L.npz"))
    np.testing.assert_allclose(traj.compressed, direct.compressed, atol=1e-9)


def test_varied_replaces_the_simulation_s_conditions_only(mesh_dir):
    traj = Trajectory.load(mesh_dir / "P0001_L.npz")
    sampler = ConditionSampler(**WIDE)
    simulation, marked = varied(FEW_STEPS, sampler, traj, "P0001_L", "mlo")
    draw = sampler.sample("P0001_L", traj.metadata["target_compression_ratio"], "mlo")
    assert simulation.materials["fat"].young == draw["materials"]["fat"]["young"]
    assert simulation.materials["skin"].membrane == 2.0
    assert (simulation.view, simulation.angle) == ("mlo", draw["angle"])
    assert simulation.compression_ratio == draw["compression_ratio"]
    assert simulation.compression_steps == FEW_STEPS.compression_steps  # the rest is kept
    assert FEW_STEPS.view == "cc" and FEW_STEPS.materials["fat"].young == 1100.0  # no mutation
    assert "variation" not in traj.metadata and marked.metadata["variation"]["view"] == "mlo"


def _recorded(materials) -> dict:
    """Materials as ``metadata["simulation"]`` records them."""
    return {k: {f: v for f, v in vars(m).items() if v is not None} for k, m in materials.items()}
