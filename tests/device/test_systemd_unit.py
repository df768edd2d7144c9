"""The systemd unit and its per-backend device drop-in: offline verification (warnings are
errors), key settings, the devices systemd itself says each backend may open, the exposure score.

The unit is installed into a temporary root by the installer so that ``ExecStart`` exists
there; ``systemd-analyze --root`` resolves paths inside that root.  Needs the ``systemd``
package (not a running systemd): ``apt-get install -y systemd``.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from stereopath.device.capture.multicast_route import ROUTE_COMMAND
from stereopath.device.service.installer import BACKEND_DROPINS, UNIT_NAME, InstallChoices, Layout, install
from tests.device.test_install import FakeVenv

pytestmark = [
    pytest.mark.timeout(60),
    pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                       reason="systemd-analyze not installed (apt-get install -y systemd)"),
]

UNIT = Path(__file__).resolve().parents[2] / "systemd" / UNIT_NAME
MAX_EXPOSURE = 1.6   # what the unit scored before the per-backend drop-in; it must not get worse
CAMERA_DEVICES = {
    "picamera2": {"char-video4linux", "char-media", "char-dma_heap"},   # libcamera
    "depthai": {"char-usb_device"},                                    # libusb, major 189
    "replay": set(), "sim": set(),
}


def _installed_root(tmp_path: Path, backend: str | None = None, config_backend: str | None = None) -> Path:
    root = tmp_path / "root"
    root.mkdir()
    if config_backend is not None:  # an admin's device.toml (kept by the installer)
        etc = root / "etc/stereopath"
        etc.mkdir(parents=True)
        (etc / "device.toml").write_text(f'[source]\nbackend = "{config_backend}"\n')
    install(root, venv=FakeVenv(), choices=InstallChoices(backend=backend))
    # what the target system provides: /bin/kill for ExecReload=, iproute2's ip for the
    # picamera2 drop-in's ExecStartPre=
    (root / "bin").mkdir()
    shutil.copy2(shutil.which("kill") or "/bin/kill", root / "bin" / "kill")
    (root / "usr/sbin").mkdir(parents=True)
    shutil.copy2(shutil.which("ip") or "/usr/sbin/ip", root / "usr/sbin" / "ip")
    return root


def _security(root: Path) -> str:
    proc = subprocess.run(["systemd-analyze", "security", "--offline=yes", f"--root={root}", "--no-pager", UNIT_NAME],
                          capture_output=True, text=True, timeout=30)
    return proc.stdout + proc.stderr


def _exposure(report: str) -> float:
    m = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", report)
    assert m, report[-2000:]
    return float(m.group(1))


def _device_acl(report: str) -> set[str]:
    """The device ACL as systemd itself assembled it from the unit and its drop-ins."""
    m = re.search(r"DeviceAllow=\s+Service has a device ACL[^:]*: (.*?)\s+\d+\.\d+\s*$", report, re.M)
    assert m, report[-3000:]
    return {item.rsplit(":", 1)[0] for item in m.group(1).split()}


def _verify(root: Path, unit: str = UNIT_NAME) -> tuple[int, str]:
    proc = subprocess.run(["systemd-analyze", "verify", "--recursive-errors=no", f"--root={root}", unit],
                          capture_output=True, text=True, timeout=30)
    return proc.returncode, (proc.stdout + proc.stderr).strip()


def _settings(text: str) -> list[tuple[str, str, str]]:
    section, out = "", []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.append((section, key.strip(), value.strip()))
    return out


def test_unit_verifies_without_any_warning(tmp_path):
    root = _installed_root(tmp_path)
    code, output = _verify(root)
    assert code == 0 and output == "", output


def test_verification_fails_on_a_warning_and_on_a_missing_executable(tmp_path):
    """The check above can fail: an unknown key, or no ExecStart binary, is reported."""
    root = _installed_root(tmp_path)
    unit_dir = root / "etc/systemd/system"
    (unit_dir / "broken.service").write_text(UNIT.read_text().replace("[Service]\n", "[Service]\nFrameRate=30\n"))
    code, output = _verify(root, "broken.service")
    assert "Unknown key" in output and "FrameRate" in output
    (root / Layout().venv.lstrip("/") / "bin" / "stereopath").unlink()
    code, output = _verify(root)
    assert code != 0 and "stereopath" in output


def test_unit_settings_the_service_relies_on():
    s = _settings(UNIT.read_text())
    get = lambda sec, key: [v for se, k, v in s if se == sec and k == key]  # noqa: E731
    assert get("Service", "Type") == ["notify"] and get("Service", "NotifyAccess") == ["main"]
    exec_start = get("Service", "ExecStart")[0].split()
    assert exec_start[0] == f"{Layout().venv}/bin/stereopath" and exec_start[1:3] == ["device", "run"]
    assert exec_start[exec_start.index("--config") + 1] == "/etc/stereopath/device.toml"
    assert float(get("Service", "WatchdogSec")[0]) > 0
    assert get("Service", "Restart") == ["on-failure"] and get("Service", "RestartPreventExitStatus") == ["78"]
    assert get("Unit", "StartLimitIntervalSec") and get("Unit", "StartLimitBurst")
    assert get("Service", "User") == ["stereopath"]
    assert set(get("Service", "SupplementaryGroups")[0].split()) == {"video", "i2c"}
    assert get("Service", "StateDirectory") == ["stereopath"] and get("Service", "RuntimeDirectory") == ["stereopath"]
    assert get("Service", "LoadCredential") == ["server.key_secret:/etc/stereopath/server.key_secret"]
    allowed = {v.split()[0] for v in get("Service", "DeviceAllow")}
    # the unit itself: only the IMU's bus; camera devices come from the backend's drop-in
    assert allowed == {"/dev/i2c-1"}
    assert get("Service", "DevicePolicy") == ["closed"]
    families = set(get("Service", "RestrictAddressFamilies")[0].split())
    assert {"AF_NETLINK", "AF_INET", "AF_UNIX"} <= families
    assert "PrivateDevices" not in {k for _, k, _ in s} and "PrivateUsers" not in {k for _, k, _ in s}
    assert get("Install", "WantedBy") == ["multi-user.target"]


def test_every_backend_has_a_drop_in_that_adds_only_device_rules():
    root = UNIT.parent
    for backend, name in BACKEND_DROPINS.items():
        s = _settings((root / name).read_text())
        pre = [v for sec, key, v in s if (sec, key) == ("Service", "ExecStartPre")]
        s = [e for e in s if e[:2] != ("Service", "ExecStartPre")]
        assert {(sec, key) for sec, key, _ in s} <= {("Service", "DeviceAllow")}, (backend, s)
        assert {v.split()[0] for _, _, v in s} == CAMERA_DEVICES[backend]
        assert all(v.split()[1] == "rw" for _, _, v in s)
        # picamera2 only: the software-sync multicast route, the same the service's refusal names
        want = ROUTE_COMMAND.replace("ip route add", "ip route replace")  # (idempotent; ip found on the unit's PATH)
        assert pre == ([f"-+{want}"] if backend == "picamera2" else []), (backend, pre)


@pytest.mark.parametrize("backend", ["picamera2", "depthai", "sim"])
def test_installed_unit_allows_exactly_the_backend_devices(tmp_path, backend):
    root = _installed_root(tmp_path, config_backend=backend)   # read from the installed device.toml
    code, output = _verify(root)
    assert code == 0 and output == "", output
    dropin = root / "etc/systemd/system" / f"{UNIT_NAME}.d" / "backend.conf"
    assert dropin.read_text() == (UNIT.parent / BACKEND_DROPINS[backend]).read_text()
    report = _security(root)
    acl = _device_acl(report)
    others = set().union(*CAMERA_DEVICES.values()) - CAMERA_DEVICES[backend]
    # USB for the OAK and not for the CSI cameras; libcamera's nodes for the CSI cameras only
    assert CAMERA_DEVICES[backend] <= acl and not others & acl, acl
    assert "/dev/i2c-1" in acl
    assert _exposure(report) <= MAX_EXPOSURE
    rule = root / Layout().udev_rules.lstrip("/")
    if backend == "depthai":
        assert 'ATTRS{idVendor}=="03e7"' in rule.read_text() and 'GROUP="stereopath"' in rule.read_text()
    else:
        assert not rule.exists()


def test_backend_option_overrides_the_configuration_and_unknown_config_is_refused(tmp_path):
    root = _installed_root(tmp_path, backend="depthai", config_backend="picamera2")
    assert "char-usb_device" in _device_acl(_security(root))
    (root / "etc/stereopath/device.toml").write_text('[source]\nbackend = "usb-cam"\n')
    from stereopath.device.errors import StereopathError

    with pytest.raises(StereopathError, match="usb-cam"):
        install(root, venv=FakeVenv())


def test_security_exposure_stays_low(tmp_path):
    root = _installed_root(tmp_path)
    assert _exposure(_security(root)) <= MAX_EXPOSURE
