"""Bad input gets one clear error that names the file or the setting, and leaves no output.

The corpus grows per command; docs/reliability.md tabulates it."""

from __future__ import annotations

from pathlib import Path

import pytest

from datamodules.trajectories import TrajectoryDataModule
from mammo_net.report import write_report


def _run_folder(root: Path, data: str) -> Path:
    run = root / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(data)
    (run / "baselines").mkdir()
    (run / "baselines" / "xgboost.json").write_text("{}")  # a model to predict with
    return run


def test_a_crafted_run_folder_executes_nothing(tmp_path):
    """The report reads plain values from a run folder's config; a `_target_` there (here one
    that would create a folder) is never called."""
    sentinel = tmp_path / "executed"
    run = _run_folder(
        tmp_path,
        f"data:\n  _target_: os.mkdir\n  path: {sentinel}\n  data_dir: {tmp_path / 'none'}\n"
        "  step: compression\n",
    )
    with pytest.raises(FileNotFoundError, match="no simulated trajectories"):
        write_report([run], tmp_path / "report", analysis=None)
    assert not sentinel.exists()
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ("data:\n  data_dir: d\n  step: [1]\n", "field 'data.step' must be str, got"),
        ("data:\n  data_dir: d\n  fold: '3'\n", "field 'data.fold' must be int or NoneType"),
        ("data: [\n", "unreadable data settings"),
        ("model: {}\n", "unreadable data settings"),
        ("data:\n  data_dir: ${hydra:runtime.cwd}\n", "unreadable data settings"),
    ],
)
def test_bad_run_folder_settings_name_the_file_and_field(tmp_path, data, message):
    run = _run_folder(tmp_path, data)
    with pytest.raises(ValueError, match=message) as info:
        TrajectoryDataModule.from_run(run)
    assert str(run / ".hydra" / "config.yaml") in str(info.value)


def test_a_folder_without_run_config_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"config.yaml: not found; is .* a train.py run"):
        TrajectoryDataModule.from_run(tmp_path)


def test_an_unwritable_output_folder_is_refused_before_the_fe_run(tmp_path, monkeypatch):
    """fem.simulate checks its output folder before simulating (not after minutes of FE)."""
    from hydra import compose, initialize_config_dir

    from fem import CONFIG_DIR
    from fem.engine import simulation
    from fem.simulate import simulate_file

    blocked = tmp_path / "file"
    blocked.write_text("")  # a file where the output folder should be
    monkeypatch.setattr(simulation.Simulation, "__call__", lambda *_: pytest.fail("simulated"))
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("simulate", [f"input={tmp_path / 'in.vtu'}", f"output={blocked / 'case'}"])
    with pytest.raises(PermissionError, match=r"file: cannot write output files there"):
        simulate_file(cfg)
