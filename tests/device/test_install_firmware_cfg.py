"""firmware_cfg/config.txt: two CSI camera overlays, I2C at 400 kHz, and never the kernel mpu6050 overlay."""

from __future__ import annotations

from pathlib import Path

CONFIG_TXT = Path(__file__).resolve().parents[2] / "firmware_cfg" / "config.txt"


def _active_lines() -> list[str]:
    return [line.split("#", 1)[0].strip() for line in CONFIG_TXT.read_text().splitlines()
            if line.split("#", 1)[0].strip()]


def test_two_camera_overlays_one_per_connector():
    overlays = [line.split("=", 1)[1] for line in _active_lines() if line.startswith("dtoverlay=")]
    cams = [o for o in overlays if o.split(",")[0] in ("imx219", "imx296", "imx477", "imx708")]
    assert len(cams) == 2
    assert sum(",cam0" in o for o in cams) == 1  # one on CAM0, the other on the default CAM1
    assert len({o.split(",")[0] for o in cams}) == 1  # same sensor model on both
    assert "camera_auto_detect=0" in _active_lines()


def test_i2c_at_400_khz_without_the_kernel_imu_driver():
    active = _active_lines()
    assert "dtparam=i2c_arm=on" in active and "dtparam=i2c_arm_baudrate=400000" in active
    assert not any("mpu6050" in line for line in active)
    text = CONFIG_TXT.read_text()
    assert "i2c-sensor,mpu6050" in text and "inv_mpu6050" in text  # the comment explaining why not
