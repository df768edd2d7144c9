"""The systemd unit: offline verification (warnings are errors), its key settings, its exposure score.

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

from stereopath.device.service.installer import UNIT_NAME, Layout, install
from tests.test_install import FakeVenv

pytestmark = [
    pytest.mark.timeout(60),
    pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                       reason="systemd-analyze not installed (apt-get install -y systemd)"),
]

UNIT = Path(__file__).resolve().parent.parent / "systemd" / UNIT_NAME
MAX_EXPOSURE = 2.0


def _installed_root(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    root.mkdir()
    install(root, venv=FakeVenv())
    # what the target system provides: /bin/kill for ExecReload=
    (root / "bin").mkdir()
    shutil.copy2(shutil.which("kill") or "/bin/kill", root / "bin" / "kill")
    return root


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
    assert {"char-video4linux", "char-media", "char-dma_heap", "/dev/i2c-1"} <= allowed
    assert get("Service", "DevicePolicy") == ["closed"]
    families = set(get("Service", "RestrictAddressFamilies")[0].split())
    assert {"AF_NETLINK", "AF_INET", "AF_UNIX"} <= families
    assert "PrivateDevices" not in {k for _, k, _ in s} and "PrivateUsers" not in {k for _, k, _ in s}
    assert get("Install", "WantedBy") == ["multi-user.target"]


def test_security_exposure_stays_low(tmp_path):
    root = _installed_root(tmp_path)
    proc = subprocess.run(["systemd-analyze", "security", "--offline=yes", f"--root={root}", "--no-pager", UNIT_NAME],
                          capture_output=True, text=True, timeout=30)
    m = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", proc.stdout + proc.stderr)
    assert m, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert float(m.group(1)) <= MAX_EXPOSURE
