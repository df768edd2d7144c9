"""The calibration commands' plots: written beside --out (or to --plot), skipped without matplotlib."""

from __future__ import annotations

import sys

import numpy as np
import pytest

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")  # IHDR width, height


def _without_matplotlib(monkeypatch) -> None:
    """Make every ``import matplotlib...`` fail as on a device without it."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


@pytest.mark.realdata
def test_calibrate_stereo_plots_the_error_of_each_pair(data_dir, tmp_path, capsys, monkeypatch):
    from stereopath.host.cli import main

    images = tmp_path / "pairs"  # six of the pairs: enough for a calibration and its plot
    images.mkdir()
    for k in ("01", "03", "04", "06", "08", "12"):
        for side in ("left", "right"):
            (images / f"{side}{k}.jpg").symlink_to(data_dir / "stereo_calib_chessboard" / f"{side}{k}.jpg")
    images = str(images)
    out = tmp_path / "rig.yaml"
    assert main(["device", "calibrate-stereo", images, "--square-mm", "25", "--out", str(out)]) == 0
    plot = tmp_path / "rig_reprojection.png"
    assert f"wrote {plot}" in capsys.readouterr().out
    w, h = _png_size(plot)
    assert 600 <= w <= 2000 and 300 <= h <= 1200
    # an explicit --plot without --out; --no-plot writes none
    other = tmp_path / "plots" / "errors.png"
    assert main(["device", "calibrate-stereo", images, "--square-mm", "25", "--plot", str(other)]) == 0
    assert _png_size(other)[0] >= 600
    plot.unlink()
    assert main(["device", "calibrate-stereo", images, "--square-mm", "25", "--out", str(out), "--no-plot"]) == 0
    assert not plot.exists()
    capsys.readouterr()
    # without matplotlib the calibration is still written and the plot is named as skipped
    out.unlink()
    _without_matplotlib(monkeypatch)
    assert main(["device", "calibrate-stereo", images, "--square-mm", "25", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and not plot.exists()
    assert "plot skipped: matplotlib is not installed" in text


def test_calibrate_stereo_plot_path_is_checked_before_the_work(tmp_path, capsys):
    from stereopath.host.cli import main

    assert main(["device", "calibrate-stereo", str(tmp_path / "none"), "--square-mm", "25",
                 "--plot", str(tmp_path)]) == 2
    assert "--plot" in capsys.readouterr().err


def test_calibrate_imu_plots_the_still_window(tmp_path, capsys, monkeypatch):
    from stereopath.host.cli import main

    out = tmp_path / "imu.yaml"
    args = ["device", "calibrate-imu", "live", "--imu", "emulated", "--seconds", "1"]
    assert main(args + ["--out", str(out)]) == 0
    plot = tmp_path / "imu_still_window.png"
    assert f"wrote {plot}" in capsys.readouterr().out
    w, h = _png_size(plot)
    assert 600 <= w <= 2000 and 300 <= h <= 1200
    other = tmp_path / "w.png"
    assert main(args + ["--plot", str(other)]) == 0 and _png_size(other)[0] >= 600
    # without matplotlib: the YAML is written, the plot skipped and said so
    plot.unlink()
    out.unlink()
    _without_matplotlib(monkeypatch)
    assert main(args + ["--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and not plot.exists()
    assert "plot skipped: matplotlib is not installed" in text


def test_still_window_plot_shades_the_window(tmp_path, monkeypatch):
    """The shaded span is the window given (read back from the figure before it is saved)."""
    pytest.importorskip("matplotlib")
    from stereopath.device.commands import calibration_plots as cp

    figures = []
    monkeypatch.setattr(cp, "_save", lambda fig, path: figures.append(fig))
    t = np.arange(0, 3_000_000_000, 5_000_000, dtype=np.int64) + 7_000_000_000
    gyro = np.zeros((len(t), 3))
    gyro[t > 8_500_000_000] = 0.5
    accel = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    assert cp.plot_still_window(tmp_path / "w.png", t, gyro, accel, (7_200_000_000, 8_400_000_000), "auto") is None
    (fig,) = figures
    gyro_axes = fig.axes[0]
    (span,) = gyro_axes.patches
    assert span.get_x() == pytest.approx(0.2) and span.get_x() + span.get_width() == pytest.approx(1.4)
    assert "0.20-1.40 s" in gyro_axes.get_title() and "(241 samples)" in gyro_axes.get_title()
    assert max(gyro_axes.lines[0].get_ydata()) == pytest.approx(np.rad2deg(0.5 * np.sqrt(3)))
