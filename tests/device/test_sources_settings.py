"""Device configuration: the documented example equals the defaults; validation names the key."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError
from stereopath.device.settings import DeviceConfig, ImuSettings, SourceSettings, load_device_config


def _keys(cls, prefix=""):
    out = set()
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            out |= _keys(type(default), key + ".")
        else:
            out.add(key)
    return out


def _toml_keys(d, prefix=""):
    out = set()
    for k, v in d.items():
        if isinstance(v, dict):
            out |= _toml_keys(v, f"{prefix}{k}.")
        else:
            out.add(f"{prefix}{k}")
    return out


def test_example_file_documents_every_key_with_its_default(repo_root):
    path = repo_root / "firmware_cfg" / "device.toml"
    assert load_device_config(path) == DeviceConfig()
    with path.open("rb") as fh:
        data = tomllib.load(fh)
    assert _toml_keys(data) == _keys(DeviceConfig)


def test_unknown_key_is_named():
    with pytest.raises(ConfigError, match="frame_rate"):
        from_mapping(DeviceConfig, {"source": {"frame_rate": 30}})


@pytest.mark.parametrize("table, key", [
    ({"source": {"fps": 0}}, "source.fps"),
    ({"source": {"fps": 30, "pair_tolerance_us": 20000}}, "source.pair_tolerance_us"),
    ({"source": {"fps": 30, "exposure_us": 40000}}, "source.exposure_us"),
    ({"imu": {"rate_hz": 300}}, "imu.rate_hz"),
    ({"imu": {"gyro_range_dps": 300}}, "imu.gyro_range_dps"),
    ({"imu": {"accel_range_g": 3}}, "imu.accel_range_g"),
    ({"imu": {"address": 0x70}}, "imu.address"),
    ({"imu": {"dlpf_cfg": 7}}, "imu.dlpf_cfg"),
    ({"imu": {"rate_hz": 1000, "read_period_ms": 100}}, "imu.read_period_ms"),
    ({"source": {"picamera2": {"buffer_count": 1}}}, "source.picamera2.buffer_count"),
])
def test_out_of_range_values_are_rejected_with_the_key(table, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        from_mapping(DeviceConfig, table)


def test_imu_divider_and_output_rate():
    s = from_mapping(ImuSettings, {"rate_hz": 200, "dlpf_cfg": 3})
    assert (s.output_rate_hz, s.smplrt_div) == (1000.0, 4)
    s = from_mapping(ImuSettings, {"rate_hz": 1000, "dlpf_cfg": 0, "read_period_ms": 20})
    assert (s.output_rate_hz, s.smplrt_div) == (8000.0, 7)


@pytest.mark.parametrize("table, ok", [
    ({"rate_hz": 2666.6666666666665, "dlpf_cfg": 0, "read_period_ms": 10}, True),   # 8 kHz / 3, 12-byte packets
    ({"rate_hz": 4000, "dlpf_cfg": 0, "read_period_ms": 10}, False),                # ~3 kHz is what 400 kHz carries
    ({"rate_hz": 2666.6666666666665, "dlpf_cfg": 0, "read_period_ms": 10, "temperature": True}, False),
    ({"rate_hz": 1000, "dlpf_cfg": 1, "i2c": {"clock_khz": 100}}, False),                       # 100 kHz: ~690 Hz
    ({"rate_hz": 500, "dlpf_cfg": 1, "i2c": {"clock_khz": 100}}, True),
])
def test_imu_rate_is_capped_by_what_the_i2c_bus_carries(table, ok):
    if ok:
        from_mapping(ImuSettings, table)
        return
    with pytest.raises(ConfigError, match=r"imu\.rate_hz = .* kHz I2C bus .* carries about \d+ Hz"):
        from_mapping(ImuSettings, table)


def test_toml_overrides_only_what_it_names(tmp_path):
    p = tmp_path / "d.toml"
    p.write_text('[source]\nbackend = "sim"\nfps = 20.0\n[imu]\nbackend = "emulated"\n')
    cfg = load_device_config(p)
    assert cfg.source.backend == "sim" and cfg.source.fps == 20.0 and cfg.imu.backend == "emulated"
    assert cfg.source.picamera2 == SourceSettings().picamera2
    assert cfg.stream.pose_endpoint == "tcp://*:5555" and cfg.stream.keyframe_endpoint == "tcp://*:5556"


def test_keys_moved_into_sub_tables_are_still_read_from_old_files(tmp_path, caplog):
    p = tmp_path / "old.toml"
    p.write_text('[stream]\nmax_credit = 4\nimage_encoding = "png"\nheartbeat_ivl_ms = 200\n'
                 '[stream.bounds]\nmax_peers = 3\n[imu]\ni2c_khz = 1000.0\nlatency_us = 50.0\n')
    with caplog.at_level("WARNING", logger="stereopath.device.settings"):
        cfg = load_device_config(p)
    assert (cfg.stream.bounds.max_credit, cfg.stream.bounds.max_peers) == (4, 3)
    assert cfg.stream.images.encoding == "png" and cfg.stream.heartbeat.ivl_ms == 200
    assert cfg.imu.i2c.clock_khz == 1000.0 and cfg.imu.timestamps.latency_us == 50.0
    assert "stream.max_credit -> stream.bounds.max_credit" in caplog.text and "imu.i2c_khz -> imu.i2c.clock_khz" in caplog.text
    p.write_text("[stream]\nmax_credit = 4\n[stream.bounds]\nmax_credit = 5\n")
    with pytest.raises(ConfigError, match=r"stream\.bounds\.max_credit .* old spelling stream\.max_credit"):
        load_device_config(p)
    with pytest.raises(ConfigError, match=r"stream\.bounds\.max_credit"):
        from_mapping(DeviceConfig, {"stream": {"bounds": {"max_credit": 0}}})
