"""``stereopath device install`` into a temporary root: the tree it makes, and that a second run changes nothing."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from stereopath.device.service.installer import UNIT_NAME, InstallChoices, InstallError, Installer, Layout, install

pytestmark = pytest.mark.timeout(60)


class FakeVenv:
    """Stands in for ``python -m venv`` + ``pip install``: the files the unit and the tests look at."""

    def __init__(self) -> None:
        self.created = 0
        self.installs = 0

    def create(self, venv_dir: Path) -> None:
        self.created += 1
        (venv_dir / "bin").mkdir(parents=True)
        (venv_dir / "pyvenv.cfg").write_text("home = /usr/bin\ninclude-system-site-packages = true\n")

    def install_project(self, venv_dir: Path, project_dir: Path) -> None:
        self.installs += 1
        launcher = venv_dir / "bin" / "stereopath"
        launcher.write_text(f"#!{Layout().venv}/bin/python\nimport sys\nfrom stereopath.host.cli import main\nsys.exit(main())\n")
        launcher.chmod(0o755)


def snapshot(root: Path) -> dict[str, tuple]:
    """Every path under ``root`` -> (kind, mode, content or link target)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            st = p.lstat()
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir", stat.S_IMODE(st.st_mode))
            else:
                out[rel] = ("file", stat.S_IMODE(st.st_mode), p.read_bytes())
    return out


def mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_install_twice_gives_the_same_tree(tmp_path):
    venv = FakeVenv()
    first = install(tmp_path, venv=venv)
    tree1 = snapshot(tmp_path)
    second = install(tmp_path, venv=venv)
    assert snapshot(tmp_path) == tree1
    assert second.changed == [] and first.changed
    assert venv.created == 1 and venv.installs == 2  # the package is (re)installed: the update path

    etc = tmp_path / "etc" / "stereopath"
    assert mode(etc / "server.key_secret") == 0o600 and mode(etc / "server.key") == 0o644
    assert b"secret-key" in (etc / "server.key_secret").read_bytes()
    assert mode(tmp_path / "var/lib/stereopath/sessions") == 0o750 and mode(etc / "clients") == 0o755
    example = Path(__file__).resolve().parents[2] / "firmware_cfg" / "device.toml"
    assert (etc / "device.toml").read_bytes() == example.read_bytes()
    link = tmp_path / "etc/systemd/system/multi-user.target.wants" / UNIT_NAME
    assert os.readlink(link) == f"/etc/systemd/system/{UNIT_NAME}"
    assert (tmp_path / "etc/systemd/system" / UNIT_NAME).read_text().startswith("# stereopath capture service")
    assert (tmp_path / "etc/modules-load.d/stereopath.conf").read_text().splitlines()[-1] == "i2c-dev"
    passwd = (tmp_path / "etc/passwd").read_text().splitlines()
    user = next(line.split(":") for line in passwd if line.startswith("stereopath:"))
    assert user[5] == "/var/lib/stereopath" and user[6] == "/usr/sbin/nologin" and 100 <= int(user[2]) < 1000
    groups = {line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/group").read_text().splitlines()}
    assert "stereopath" in groups["video"][3].split(",") and "stereopath" in groups["i2c"][3].split(",")
    assert groups["stereopath"][2] == user[3]


def test_existing_accounts_and_edited_config_are_kept(tmp_path):
    (tmp_path / "etc/stereopath").mkdir(parents=True)
    (tmp_path / "etc/passwd").write_text("root:x:0:0:root:/root:/bin/bash\npi:x:1000:1000::/home/pi:/bin/bash\n"
                                         "systemd-network:x:999:999::/:/usr/sbin/nologin\n")
    (tmp_path / "etc/group").write_text("root:x:0:\nvideo:x:44:pi\ni2c:x:998:pi\nsystemd-network:x:999:\n")
    (tmp_path / "etc/stereopath/device.toml").write_text("[source]\nbackend = \"depthai\"\n")
    install(tmp_path, venv=FakeVenv())
    groups = {line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/group").read_text().splitlines()}
    assert groups["video"] == ["video", "x", "44", "pi,stereopath"] and groups["i2c"][3] == "pi,stereopath"
    user = next(line.split(":") for line in (tmp_path / "etc/passwd").read_text().splitlines()
                if line.startswith("stereopath:"))
    assert user[2] not in ("0", "1000", "999", "998")  # a free system id
    assert (tmp_path / "etc/passwd").read_text().startswith("root:x:0:0:root:/root:/bin/bash\npi:")
    assert (tmp_path / "etc/stereopath/device.toml").read_text() == "[source]\nbackend = \"depthai\"\n"


def test_dry_run_changes_nothing(tmp_path):
    report = Installer(tmp_path, venv=FakeVenv(), choices=InstallChoices(dry_run=True)).run()
    assert report.changed and list(tmp_path.iterdir()) == []


def test_a_command_run_is_not_a_change_and_the_dry_run_says_what_is_not_there_yet(tmp_path, capsys):
    """On the live root pip runs each time: a rerun still reports "already installed" when no file changed."""
    from stereopath.device.service.installer import InstallReport
    from stereopath.host.cli import main

    rep = InstallReport(tmp_path, actions=[f"keep {tmp_path}/opt/stereopath/venv", "run pip install . into /opt/x"])
    assert rep.changed == []
    assert main(["device", "install", "--root", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "server.key (once installed)" in out and "would create" in out


def test_half_a_key_pair_is_refused(tmp_path):
    (tmp_path / "etc/stereopath").mkdir(parents=True)
    (tmp_path / "etc/stereopath/server.key").write_text("public only\n")
    with pytest.raises(InstallError, match="server.key exists without its pair"):
        install(tmp_path, venv=FakeVenv())


@pytest.mark.skipif(not Path("/usr/bin/python3").exists(), reason="no system /usr/bin/python3 to make a venv from")
def test_default_venv_outside_slash_is_cheap_and_touches_no_system(tmp_path):
    """Without an injected builder, a non-/ root gets a pip-less venv and no command runs on this system."""
    ran: list[list[str]] = []

    def runner(cmd):
        ran.append(list(cmd))
        if "venv" in cmd:
            import subprocess

            subprocess.run(cmd, check=True)

    Installer(tmp_path, runner=runner, choices=InstallChoices(python=os.path.realpath("/usr/bin/python3"))).run()
    assert len(ran) == 1 and "--without-pip" in ran[0] and "--system-site-packages" in ran[0]
    cfg = (tmp_path / "opt/stereopath/venv/pyvenv.cfg").read_text()
    assert "include-system-site-packages = true" in cfg


def test_host_keys_are_authorised_and_secrets_refused(tmp_path):
    from stereopath.device.wire.security import generate_keypair

    pub, sec = generate_keypair(tmp_path / "laptop", "laptop")
    root = tmp_path / "root"
    root.mkdir()
    install(root, venv=FakeVenv(), choices=InstallChoices(host_keys=[pub]))
    copied = root / "etc/stereopath/clients/laptop.key"
    assert copied.read_bytes() == pub.read_bytes() and mode(copied) == 0o644
    assert install(root, venv=FakeVenv(), choices=InstallChoices(host_keys=[pub])).changed == []
    with pytest.raises(InstallError, match="never a .key_secret"):
        install(root, venv=FakeVenv(), choices=InstallChoices(host_keys=[sec]))
