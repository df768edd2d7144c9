from dataclasses import dataclass, field

import pytest

from stereopath.device.core.config import check_range, from_mapping, load_toml, replace
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
