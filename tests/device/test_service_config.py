"""Capture-service configuration: command-line overrides, file-system checks, reload split, status file."""

from __future__ import annotations

import json
import os
import stat
from dataclasses import replace

import pytest

from stereopath.device.errors import ConfigError
from stereopath.device.service.options import RunOptions, apply_options, check_config, load_config, secret_key_path, \
    split_changes
from stereopath.device.service.status import status_line, write_status_file
from stereopath.device.settings import DeviceConfig
from stereopath.device.wire.security import generate_keypair


def test_source_overrides_pick_the_recordings_own_imu():
    cfg = apply_options(DeviceConfig(), RunOptions(source="replay:session:/data/s1"))
    assert cfg.source.backend == "replay" and cfg.source.replay.path == "session:/data/s1"
    assert cfg.imu.backend == "source"
    cfg = apply_options(DeviceConfig(), RunOptions(source="sim", imu="none", stream=False, insecure=True, drain_s=0))
    assert (cfg.source.backend, cfg.imu.backend, cfg.stream.enabled, cfg.stream.insecure, cfg.stream.drain_s) == \
        ("sim", "none", False, True, 0.0)
    cfg = apply_options(DeviceConfig(), RunOptions(source="depthai"))
    assert cfg.imu.backend == "mpu6050"  # a real camera keeps the configured IMU
    with pytest.raises(ConfigError, match="--source 'usb'"):
        apply_options(DeviceConfig(), RunOptions(source="usb"))
    with pytest.raises(ConfigError, match="--frames"):
        RunOptions(frames=0)


def test_precedence_defaults_file_command_line(tmp_path):
    f = tmp_path / "d.toml"
    f.write_text('[source]\nbackend = "sim"\nfps = 20.0\n[service]\nstatus_file = "/tmp/a.json"\n')
    cfg = load_config(f, RunOptions(status_file=""))
    assert cfg.source.fps == 20.0 and cfg.source.exposure_us == 8000 and cfg.service.status_file == ""


def test_file_checks_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="keys.server_secret"):
        check_config(DeviceConfig(), environ={})
    pub, sec = generate_keypair(tmp_path / "dev", "server")
    clients = tmp_path / "clients"
    clients.mkdir()
    cfg = DeviceConfig()

    cfg = replace(cfg, keys=replace(cfg.keys, server_secret=str(sec), clients_dir=str(clients)))
    with pytest.raises(ConfigError, match="keys.clients_dir .* no host public key"):
        check_config(cfg, environ={})
    generate_keypair(clients, "laptop")
    (clients / "laptop.key_secret").unlink()
    check_config(cfg, environ={})
    bad = replace(cfg, stream=replace(cfg.stream, insecure=True, pose_endpoint="tcp://0.0.0.0:5555"))
    with pytest.raises(ConfigError, match="stream.pose_endpoint"):
        check_config(bad, environ={})
    with pytest.raises(ConfigError, match="source.rig_file"):
        check_config(replace(cfg, source=replace(cfg.source, rig_file=str(tmp_path / "nope.yaml"))), environ={})


def test_the_systemd_credential_wins_over_the_configured_key(tmp_path):
    cred = tmp_path / "creds"
    cred.mkdir()
    cfg = DeviceConfig()
    assert str(secret_key_path(cfg, {"CREDENTIALS_DIRECTORY": str(cred)})) == cfg.keys.server_secret  # not there yet
    (cred / "server.key_secret").write_text("x")
    assert secret_key_path(cfg, {"CREDENTIALS_DIRECTORY": str(cred)}) == cred / "server.key_secret"


def test_reload_split_live_and_restart_keys():
    old = DeviceConfig()
    new = load_config(None, RunOptions(source="sim"))
    new = replace(new, timealign=replace(new.timealign, time_offset_us=250.0),
                  recorder=replace(new.recorder, reserve_mb=100.0))
    live, restart = split_changes(old, new)
    assert live == ["recorder.reserve_mb", "timealign.time_offset_us"]
    assert restart == ["imu.backend", "source.backend"]


def test_status_file_is_atomic_and_world_readable(tmp_path):
    old = os.umask(0o027)  # the unit's UMask
    try:
        write_status_file(tmp_path / "status.json", {"state": "running"})
    finally:
        os.umask(old)
    p = tmp_path / "status.json"
    assert stat.S_IMODE(p.stat().st_mode) == 0o644 and p.read_text().strip().startswith("{")
    assert [q.name for q in tmp_path.iterdir()] == ["status.json"]
    line = status_line({"state": "running", "session_id": "s1", "frame_rate_hz": 19.96, "imu_rate_hz": 200.4,
                        "dropped_frames": 2, "imu_gaps": 1, "tracking": "ok", "cpu_process_pct": 71.0,
                        "temperature_c": 55.25, "disk_free_bytes": 12_300_000_000, "recorder_state": "recording",
                        "hosts": 1})
    assert line == ("running s1: 20.0 fps, IMU 200 Hz, 2 dropped, 1 IMU gaps, tracking ok, CPU 71%, 55.2 C, "
                    "12.3 GB free, recorder recording, 1 host(s)")
    assert "\n" not in line


def test_journal_lines_carry_the_syslog_priority_and_stay_on_one_line():
    import logging

    from stereopath.device.service.journal import JournalFormatter as _JournalFormatter

    fmt = _JournalFormatter("%(levelname)s %(name)s: %(message)s")
    rec = logging.LogRecord("stereopath.device.service.service", logging.ERROR, __file__, 1, "camera lost\nagain", None, None)
    assert fmt.format(rec) == "<3>ERROR stereopath.device.service.service: camera lost | again"
    rec = logging.LogRecord("stereopath.device.service.service", logging.WARNING, __file__, 1, "low disk", None, None)
    assert fmt.format(rec).startswith("<4>WARNING")


def test_estimator_name_and_its_old_spelling(tmp_path):
    new = tmp_path / "new.toml"
    new.write_text('[estimator]\nname = "stereo"\n')
    old = tmp_path / "old.toml"
    old.write_text('[estimator]\npreset = "stereo"\n')
    both = tmp_path / "both.toml"
    both.write_text('[estimator]\npreset = "stereo"\nname = "stereo"\n')
    baseline = tmp_path / "baseline.toml"
    baseline.write_text('[estimator]\nname = "sfm"\n')
    assert load_config(new, RunOptions()).estimator.name == "stereo"
    assert load_config(old, RunOptions()).estimator.name == "stereo"
    with pytest.raises(ConfigError, match="preset"):
        load_config(both, RunOptions())
    with pytest.raises(ConfigError, match="host-side"):
        load_config(baseline, RunOptions())


@pytest.mark.parametrize("field,option", [("wait_for_host_s", "--wait-for-host"), ("drain_s", "--drain"),
                                          ("duration_s", "--duration")])
def test_run_options_refuse_nan(field, option):
    """``--wait-for-host nan`` used to be taken (every comparison with nan is false)."""
    with pytest.raises(ConfigError, match=option):
        RunOptions(**{field: float("nan")})


def test_device_status_keeps_stdout_for_the_report(tmp_path, capsys):
    """`device status --json` prints JSON only (a script parses it); warnings and errors go to stderr."""
    import time

    from stereopath.host.cli import main

    st = tmp_path / "status.json"
    report = {"state": "running", "updated_unix": time.time(), "status_interval_s": 1.0}
    st.write_text(json.dumps(report))
    assert main(["device", "status", "--status-file", str(st), "--json"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["state"] == "running" and out.err == ""
    st.write_text(json.dumps({**report, "updated_unix": time.time() - 600}))  # the service stopped writing it
    assert main(["device", "status", "--status-file", str(st), "--json"]) == 1
    out = capsys.readouterr()
    assert json.loads(out.out)["state"] == "running" and "WARNING: the report is 6" in out.err
    assert main(["device", "status", "--status-file", str(tmp_path / "none.json")]) == 1
    out = capsys.readouterr()
    assert out.out == "" and "the capture service is not running" in out.err
