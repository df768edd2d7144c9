"""docs/make_wiring.py: the wiring SVG follows firmware_cfg/device.toml's [imu] bus and address."""

from __future__ import annotations

import importlib.util
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture(scope="module")
def wiring():
    key = "_docs_make_wiring"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, ROOT / "docs" / "make_wiring.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[key] = mod
        spec.loader.exec_module(mod)
    return sys.modules[key]


def _texts(svg: str) -> list[str]:
    return [t.text for t in ET.fromstring(svg).iter(f"{SVG}text")]


def test_the_drawing_shows_the_configured_pins_and_address(wiring):
    bus, address = wiring.imu_settings(ROOT / "firmware_cfg" / "device.toml")
    assert (bus, address) == (1, 0x68)
    texts = _texts(wiring.draw(bus, address))
    for wire in ("pin 1 3V3 -> VCC", "pin 6 GND -> GND", "pin 3 GPIO2 / SDA1 -> SDA", "pin 5 GPIO3 / SCL1 -> SCL"):
        assert wire in texts
    assert "AD0 to GND" in texts and "I2C: /dev/i2c-1, address 0x68" in texts
    assert "left camera -> CAM/DISP 0" in texts and "right camera -> CAM/DISP 1" in texts


def test_address_0x69_ties_ad0_high_and_bad_addresses_are_refused(wiring, tmp_path):
    texts = _texts(wiring.draw(3, 0x69))
    assert "AD0 to VCC" in texts and "I2C: /dev/i2c-3, address 0x69" in texts
    bad = tmp_path / "device.toml"
    bad.write_text("[imu]\naddress = 0x50\n")
    with pytest.raises(SystemExit, match="imu.address = 0x50"):
        wiring.imu_settings(bad)


def test_committed_svg_is_what_the_script_draws(wiring):
    committed = (ROOT / "docs" / "img" / "wiring.svg").read_text(encoding="utf-8")
    assert committed == wiring.draw(*wiring.imu_settings(ROOT / "firmware_cfg" / "device.toml"))
