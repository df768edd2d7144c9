from dataclasses import dataclass, field

import pytest

from stereopath.device.core.config import check_range, check_ranges, field_range, from_mapping, load_toml, ranged, replace
from stereopath.device.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    rate_hz: float = 200.0

    def __post_init__(self):
        check_range("imu.rate_hz", self.rate_hz, 1, 1000)


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    frames: int = 10
    views: tuple[tuple[float, float], ...] = ((1.0, 0.0),)
    imu: Inner = field(default_factory=Inner)


def test_builds_nested_and_converts():
    c = from_mapping(Outer, {"frames": 5, "views": [[2, 30]], "imu": {"rate_hz": 100}})
    assert c.frames == 5 and c.views == ((2.0, 30.0),) and c.imu.rate_hz == 100.0


@pytest.mark.parametrize("data, match", [
    ({"frame": 3}, "frame"),
    ({"imu": {"rate": 3}}, "imu"),
    ({"frames": "3"}, "frames"),
    ({"frames": True}, "frames"),
    ({"imu": {"rate_hz": 5000}}, "imu.rate_hz"),
    ({"views": [[1, 2, 3]]}, "views"),
])
def test_rejects_bad_input_naming_the_key(data, match):
    with pytest.raises(ConfigError, match=match):
        from_mapping(Outer, data)


def test_replace_validates():
    c = from_mapping(Outer, {})
    assert replace(c, frames=3).frames == 3
    with pytest.raises(ConfigError):
        replace(c, nope=1)


def test_load_toml_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_toml(tmp_path / "x.toml")
    (tmp_path / "bad.toml").write_text("a = [")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_toml(tmp_path / "bad.toml")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf"), 10**400])
def test_rejects_non_finite_floats_naming_the_key(value):
    with pytest.raises(ConfigError, match=r"imu\.rate_hz must be a finite number"):
        from_mapping(Outer, {"imu": {"rate_hz": value}})
    with pytest.raises(ConfigError, match=r"views\[0\]\[1\] must be a finite number"):
        from_mapping(Outer, {"views": [[1.0, value]]})


def test_check_range_rejects_nan():
    with pytest.raises(ConfigError, match="imu.rate_hz = nan"):
        Inner(rate_hz=float("nan"))


@pytest.mark.parametrize("section, key", [
    ("source", "fps"), ("source", "timeout_s"), ("imu", "rate_hz"), ("recorder", "reserve_mb"),
    ("timealign", "max_wait_ms"), ("selftest", "still_s"), ("selftest", "max_gyro_bias_dps"),
])
def test_device_toml_rejects_nan_and_inf(tmp_path, section, key):
    from stereopath.device.settings import load_device_config
    for text in ("nan", "inf", "-inf"):
        path = tmp_path / "device.toml"
        path.write_text(f"[{section}]\n{key} = {text}\n")
        with pytest.raises(ConfigError, match=rf"{section}\.{key} must be a finite number"):
            load_device_config(path)


def test_load_toml_unreadable_files(tmp_path):
    (tmp_path / "bin.toml").write_bytes(b"\x84\xff\x00 = 1\n")
    with pytest.raises(ConfigError, match="bin.toml: not a UTF-8"):
        load_toml(tmp_path / "bin.toml")
    with pytest.raises(ConfigError, match="is a folder"):
        load_toml(tmp_path)


@dataclass(frozen=True)
class _Ranged:
    depth_m: float = ranged(5.0, 0.1, 100.0)
    levels: tuple[int, ...] = ranged((1, 2), 1, 8)
    cap: int | None = ranged(None, 1)
    free: float = 1.0

    def __post_init__(self) -> None:
        check_ranges(self, "section.")


def test_ranges_are_declared_once_with_the_field():
    assert field_range(_Ranged, "depth_m") == (0.1, 100.0)
    assert field_range(_Ranged, "free") is None
    assert from_mapping(_Ranged, {"depth_m": 0.1, "levels": [8], "cap": 3, "free": -9.0}).cap == 3
    for data, match in (({"depth_m": 0.05}, r"section\.depth_m = 0\.05 is out of range \[0\.1, 100\.0\]"),
                        ({"levels": [1, 9]}, r"section\.levels\[1\] = 9"),
                        ({"cap": 0}, r"section\.cap = 0"),
                        ({"depth_m": float("nan")}, "depth_m")):
        with pytest.raises(ConfigError, match=match):
            from_mapping(_Ranged, data)
    with pytest.raises(ConfigError, match="depth_m"):
        replace(_Ranged(), depth_m=1e6)
