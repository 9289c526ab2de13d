import math

from matplotlib.image import imread

from fem.breasts.figures import simulation_summary_png


def _row(name, status, volume, t1, t2, ratio, reason=""):
    return {
        "name": name,
        "status": status,
        "reason": reason,
        "volume_cm3": volume,
        "time_unloaded_s": t1,
        "time_compression_s": t2,
        "compression_ratio": ratio,
        "target_compression_ratio": 0.5,
    }


def test_simulation_summary_png(tmp_path):
    rows = [
        _row("p001_L", "ok", 450.0, 12.0, 40.0, 0.48),
        _row("p001_R", "ok", 520.0, 14.5, 55.0, 0.52),
        _row("p002_L", "ok", 1300.0, 30.0, 150.0, 0.61),
        _row("p003_R", "failed", 2100.0, 45.0, math.nan, math.nan, "Newton did not converge"),
    ]
    path = tmp_path / "figs" / "simulation.png"
    assert simulation_summary_png(rows, path) == path
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 300
    assert [p.name for p in path.parent.iterdir()] == ["simulation.png"]


def test_simulation_summary_png_all_failed(tmp_path):
    rows = [_row("p9_L", "failed", 800.0, 20.0, math.nan, math.nan, "")]
    path = tmp_path / "all_failed.png"
    simulation_summary_png(rows, path)
    assert imread(path).shape[:2] == (675, 990)
