"""stereopath device selftest: pass/fail table over injected fakes and the simulator."""

from __future__ import annotations

import pytest

from stereopath.device.commands.selftest import format_table, run_selftest
from stereopath.device.core.config import from_mapping
from stereopath.device.capture.imu.emulator import Mpu6050Emulator, SimClock, still_source
from stereopath.device.capture.imu.mpu6050 import Mpu6050
from stereopath.device.settings import DeviceConfig
from stereopath.device.capture.sources import create_source
from tests.fakes.fake_picamera2 import FakeCameraWorld
from tests.fakes.standins import StandinSequence

pytestmark = pytest.mark.timeout(60)


def config(**sections):
    base = {"source": {"backend": "sim", "fps": 20.0}, "imu": {"backend": "emulated"},
            "selftest": {"frames": 10}, "recorder": {"dir": "/tmp"}}
    for k, v in sections.items():
        base.setdefault(k, {}).update(v)
    return from_mapping(DeviceConfig, base)


def by_name(checks):
    return {c.name: c for c in checks}


def test_all_checks_pass_on_a_healthy_simulated_unit():
    cfg = config()
    src = create_source(cfg.source, session=StandinSequence(n=12, fps=20.0))
    checks = by_name(run_selftest(cfg, source=src))
    assert all(c.ok for c in checks.values()), format_table(list(checks.values()))
    assert set(checks) >= {"camera open", "frame pairing", "camera rate", "IMU WHO_AM_I", "IMU rate",
                           "gyro bias", "gyro still", "gravity magnitude", "free disk"}
    assert checks["IMU WHO_AM_I"].value == "0x68"


def test_failures_are_reported_in_the_table():
    cfg = config(recorder={"reserve_mb": 1e7}, selftest={"max_gyro_bias_dps": 0.1})
    clk = SimClock()
    bad_imu = Mpu6050(cfg.imu, bus=Mpu6050Emulator(clk, still_source(), who_am_i=0x42), clock_ns=clk.now_ns,
                      sleep=clk.sleep)
    checks = by_name(run_selftest(cfg, source=create_source(cfg.source, session=StandinSequence(n=12)),
                                  imu=bad_imu))
    assert not checks["IMU open"].ok and "0x42" in checks["IMU open"].value
    assert not checks["free disk"].ok
    table = format_table(list(checks.values()))
    assert "FAIL" in table and "PASS" in table
    cfg2 = config(selftest={"max_gyro_bias_dps": 0.1})
    checks2 = by_name(run_selftest(cfg2, source=create_source(cfg2.source, session=StandinSequence(n=12))))
    assert not checks2["gyro bias"].ok and checks2["gravity magnitude"].ok   # emulated bias 0.8 deg/s


def test_picamera2_pairing_and_rate_through_the_fake():
    cfg = config(source={"backend": "picamera2", "fps": 50.0, "exposure_us": 2000, "pair_tolerance_us": 500,
                         "size": [32, 24], "picamera2": {"sync_frames": 30}}, imu={"backend": "none"})
    world = FakeCameraWorld()
    world.cameras[1].drop = frozenset({36})  # after SyncReady (30 frames, tests/fakes/standins.py)
    checks = by_name(run_selftest(cfg, source=create_source(cfg.source, api=world.api())))
    assert checks["frame pairing"].ok and checks["camera rate"].ok and "1 unpaired" in checks["frame pairing"].value
    assert checks["IMU"].ok and checks["IMU"].value == "none configured"


def _picamera2_config(**picamera2):
    return config(source={"backend": "picamera2", "fps": 50.0, "exposure_us": 2000, "pair_tolerance_us": 500,
                          "size": [32, 24], "picamera2": {"sync_frames": 30, **picamera2}},
                  imu={"backend": "none"}, selftest={"frames": 4})


def test_picamera2_selftest_shows_the_sync_state_and_the_left_camera():
    cfg = _picamera2_config()
    world = FakeCameraWorld()
    checks = by_name(run_selftest(cfg, source=create_source(cfg.source, api=world.api())))
    sync = checks["camera sync"]
    assert sync.ok and "route via lo" in sync.value and "SyncFrames 30" in sync.value, sync
    assert "SyncReady after" in sync.value and "max skew 0 us" in sync.value
    left = checks["left camera"]
    # the fake's Pi 5 Ids: position 0 of global_camera_info() is rp1/i2c@88000, the CAM/DISP 0 connector
    assert left.ok and left.value.startswith(f"left {world.cameras[0].id} (CAM/DISP 0), right {world.cameras[1].id} "
                                             "(CAM/DISP 1)"), left


def test_picamera2_selftest_names_the_missing_route():
    cfg = _picamera2_config()
    world = FakeCameraWorld(multicast_route=False)
    src = create_source(cfg.source, api=world.api(), route_reader=lambda: "Iface\tDestination\n")
    checks = by_name(run_selftest(cfg, source=src))
    assert not checks["camera open"].ok and "239.255.255.250" in checks["camera open"].value


@pytest.mark.parametrize("covered, swap_ids, verdict", [
    (0, False, "left image darker"), (0, True, "swapped"), (None, False, "neither image darker")])
def test_cover_left_finds_swapped_cameras(covered, swap_ids, verdict):
    import numpy as np

    world = FakeCameraWorld()
    bright, dark = np.full((24, 32), 180, np.uint8), np.full((24, 32), 20, np.uint8)
    world.images = [tuple(dark if num == covered else bright for num in (0, 1))]  # by libcamera Num
    ids = {"left_id": world.cameras[1].id, "right_id": world.cameras[0].id} if swap_ids else {}
    cfg = _picamera2_config(**ids)
    checks = by_name(run_selftest(cfg, source=create_source(cfg.source, api=world.api()), cover_left=True))
    left = checks["left camera"]
    assert left.ok == (verdict == "left image darker") and verdict in left.value, left


def test_lost_camera_fails_the_pairing_check():
    cfg = config(source={"backend": "picamera2", "fps": 50.0, "exposure_us": 2000, "pair_tolerance_us": 500,
                         "size": [32, 24], "timeout_s": 0.3, "picamera2": {"sync_frames": 30}},
                 imu={"backend": "none"})
    world = FakeCameraWorld()
    world.cameras[0].disappear_after = 3
    checks = by_name(run_selftest(cfg, source=create_source(cfg.source, api=world.api())))
    assert not checks["frame pairing"].ok and "left camera" in checks["frame pairing"].value


def test_cli_selftest_with_the_simulator(capsys, tmp_path):
    from stereopath.host.cli import main

    cfgfile = tmp_path / "d.toml"
    cfgfile.write_text(f'[recorder]\ndir = "{tmp_path}"\nreserve_mb = 1.0\n')
    rc = main(["device", "selftest", "--config", str(cfgfile), "--source", "sim", "--frames", "5"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "checks passed" in out and "FAIL" not in out and "IMU WHO_AM_I" in out
    cfgfile.write_text(f'[recorder]\ndir = "{tmp_path}"\nreserve_mb = 1e7\n')
    assert main(["device", "selftest", "--config", str(cfgfile), "--source", "sim", "--frames", "5"]) == 1


def test_selftest_checks_the_installed_configuration_and_replays_with_the_recordings_imu(tmp_path, monkeypatch, capsys):
    """Without --config the installed /etc/stereopath/device.toml is what is checked (as `device status`
    reads it); --source replay:SPEC takes the recording's own IMU, as `device run` does."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device import settings
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.cli import main

    toml = tmp_path / "device.toml"
    toml.write_text(f'[source]\nbackend = "sim"\n[imu]\nbackend = "emulated"\n[selftest]\nframes = 12\n'
                    f'[recorder]\ndir = "{tmp_path / "sessions"}"\n')
    monkeypatch.setattr(settings, "INSTALLED_CONFIG", str(toml))
    assert main(["device", "selftest"]) == 0
    out = capsys.readouterr().out
    assert "12 pairs" in out and f"({tmp_path / 'sessions'} does not exist yet)" in out
    record_sequence(open_sim(SimConfig(frames=14)), tmp_path / "rec", config_dict={"source": "sim"})
    main(["device", "selftest", "--source", f"replay:session:{tmp_path / 'rec'}"])
    out = capsys.readouterr().out
    assert "IMU rate" in out and "WHO_AM_I" not in out  # no MPU-6050 opened: the recording's samples
    monkeypatch.setattr(settings, "INSTALLED_CONFIG", str(tmp_path / "absent.toml"))
    assert settings.config_or_installed(None) is None and settings.config_or_installed("x.toml") == "x.toml"
