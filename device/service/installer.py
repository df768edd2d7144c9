"""Install the capture service on a device (or into a directory tree standing in for one).

:func:`install` makes, under ``root`` (``/`` on the device, a temporary folder in tests):

========================================================  =====  =============================
``etc/passwd``, ``etc/group``                              user ``stereopath`` (system), in groups video, i2c
``opt/stereopath/venv/``                                   venv with ``--system-site-packages`` (apt picamera2)
``etc/stereopath/device.toml``                             0644   from firmware_cfg/device.toml, never overwritten
``etc/stereopath/server.key`` / ``server.key_secret``      0644 / 0600  device CURVE pair, never overwritten
``etc/stereopath/clients/``                                0755   authorised host public keys (``*.key``)
``var/lib/stereopath/sessions/``                           0750   recordings (owner stereopath)
``etc/modules-load.d/stereopath.conf``                     0644   loads i2c-dev at boot
``etc/systemd/system/stereopath-capture.service``          0644   the unit
``etc/systemd/system/stereopath-capture.service.d/``       0644   ``backend.conf``: the devices the configured
``backend.conf``                                                  ``source.backend`` needs (``systemd/backend-*.conf``)
``etc/udev/rules.d/80-stereopath-oak.rules``               0644   depthai only: the OAK's USB node for the user
``etc/systemd/system/multi-user.target.wants/...``         link   enabled at boot
========================================================  =====  =============================

The unit itself allows only the IMU's I2C bus (``DevicePolicy=closed``); the drop-in adds
exactly what the camera backend in ``/etc/stereopath/device.toml`` opens: libcamera's V4L2,
media-controller and DMA-heap nodes for ``picamera2``, USB device nodes
(``char-usb_device``) for ``depthai``, nothing for ``replay`` and ``sim``.  The
``picamera2`` drop-in also adds, before each start, a host route for libcamera's
software-sync multicast group through the loopback interface (``ExecStartPre=`` with
``ip route replace 239.255.255.250/32 dev lo``), which a box with no network up lacks.  Run the
installer again after changing ``source.backend``.

Every step first looks at what is there and only changes what differs, so running it again
gives the same tree (and reports every step as ``keep``).  With ``root == "/"`` the user and
groups are made with ``groupadd``/``useradd``, owners are set, the package is installed into
the venv with pip and ``systemctl daemon-reload`` runs; under any other root the account
entries are written into ``ROOT/etc/passwd`` and ``ROOT/etc/group``, nothing is chowned and no
command touches the running system.  The venv builder and the command runner are injectable.
The Raspberry Pi firmware settings (``firmware_cfg/config.txt``) are not edited: the report
says where to append them.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol, Sequence

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.formats.fileio import write_atomic

log = logging.getLogger(__name__)

UNIT_NAME = "stereopath-capture.service"
# source.backend -> the drop-in (in systemd/) that allows that backend's devices
BACKEND_DROPINS = {"picamera2": "backend-picamera2.conf", "depthai": "backend-depthai.conf",
                   "replay": "backend-none.conf", "sim": "backend-none.conf"}
OAK_USB_VENDOR = "03e7"  # Intel Movidius: the OAK before and after its firmware boots
REPO_ROOT = Path(__file__).resolve().parents[2]


class InstallError(StereopathError):
    """A step of the installation failed (the message names it)."""


@dataclass(frozen=True)
class Layout:
    """Where things go on the device (absolute paths, resolved under the install root)."""

    user: str = "stereopath"
    groups: tuple[str, ...] = ("video", "i2c")
    prefix: str = "/opt/stereopath"
    etc_dir: str = "/etc/stereopath"
    state_dir: str = "/var/lib/stereopath"
    unit_dir: str = "/etc/systemd/system"
    modules_load: str = "/etc/modules-load.d/stereopath.conf"
    udev_rules: str = "/etc/udev/rules.d/80-stereopath-oak.rules"
    nologin: str = "/usr/sbin/nologin"

    @property
    def venv(self) -> str:
        return f"{self.prefix}/venv"

    @property
    def sessions(self) -> str:
        return f"{self.state_dir}/sessions"


class VenvBuilder(Protocol):
    def create(self, venv_dir: Path) -> None:
        """Make a virtual environment with access to the system site packages."""

    def install_project(self, venv_dir: Path, project_dir: Path) -> None:
        """Install (or upgrade) the stereopath package into it."""


Runner = Callable[[Sequence[str]], None]


def run_command(cmd: Sequence[str]) -> None:
    """Run a command, turning failure into :class:`InstallError` with its output."""
    try:
        proc = subprocess.run(list(cmd), capture_output=True, text=True, check=False)
    except OSError as exc:
        raise InstallError(f"cannot run {cmd[0]}: {exc}") from None
    if proc.returncode != 0:
        detail = (proc.stderr or proc.stdout).strip().splitlines()
        raise InstallError(f"{' '.join(cmd)} failed (exit {proc.returncode}): {detail[-1] if detail else ''}")


@dataclass
class SystemVenv:
    """``python -m venv --system-site-packages`` with the system Python (the one apt's picamera2 is for)."""

    python: str = "/usr/bin/python3"
    with_pip: bool = True
    runner: Runner = run_command

    def create(self, venv_dir: Path) -> None:
        cmd = [self.python, "-m", "venv", "--system-site-packages"]
        if not self.with_pip:
            cmd.append("--without-pip")
        self.runner([*cmd, str(venv_dir)])

    def install_project(self, venv_dir: Path, project_dir: Path) -> None:
        if not self.with_pip:
            log.warning("venv made without pip: install the stereopath package into %s on the device", venv_dir)
            return
        self.runner([str(venv_dir / "bin" / "python"), "-m", "pip", "install", "--upgrade", "--quiet",
                     str(project_dir)])


@dataclass
class InstallReport:
    root: Path
    actions: list[str] = field(default_factory=list)   # "create PATH", "keep PATH", "update PATH", "run CMD"
    device_public_key: Path | None = None

    @property
    def changed(self) -> list[str]:
        """Files and folders created or updated (commands run, such as pip, are actions but not changes)."""
        return [a for a in self.actions if not a.startswith(("keep ", "run "))]


@dataclass(frozen=True)
class InstallChoices:
    """What ``stereopath device install`` is asked for: report only (``dry_run``), the system Python the
    venv is made from, host public keys to authorise, the camera backend (None: ``source.backend`` of the
    installed device.toml)."""

    dry_run: bool = False
    python: str = "/usr/bin/python3"
    host_keys: Sequence[str | Path] = ()
    backend: str | None = None


class Installer:
    """One installation run (see the module doc); :meth:`run` does every step in order."""

    def __init__(self, root: str | Path = "/", *, layout: Layout | None = None, venv: VenvBuilder | None = None,
                 runner: Runner | None = None, project_dir: str | Path | None = None,
                 choices: InstallChoices = InstallChoices()) -> None:
        self.root = Path(root).resolve()
        self.live = self.root == Path("/")
        self.layout = layout or Layout()
        self.runner = runner or run_command
        self.venv = venv or SystemVenv(python=choices.python, with_pip=self.live, runner=self.runner)
        self.project_dir = Path(project_dir) if project_dir else REPO_ROOT
        self.dry_run = choices.dry_run
        self.host_keys = [Path(k) for k in choices.host_keys]
        self.backend = choices.backend  # None: source.backend of the installed device.toml
        self.report = InstallReport(self.root)

    # ------------------------------------------------------------------ helpers

    def path(self, absolute: str) -> Path:
        """``absolute`` (a path on the device) under the install root."""
        return self.root / absolute.lstrip("/")

    def _note(self, verb: str, what: str | Path) -> None:
        shown = what if isinstance(what, str) else "/" + Path(what).relative_to(self.root).as_posix()
        self.report.actions.append(f"{verb} {shown}")
        log.debug("%s%s %s", "[dry run] " if self.dry_run and verb != "keep" else "", verb, shown)

    def _run(self, cmd: Sequence[str]) -> None:
        self._note("run", " ".join(cmd))
        if not self.dry_run:
            self.runner(cmd)

    def _dir(self, absolute: str, mode: int, owner: str | None = None) -> None:
        p = self.path(absolute)
        if p.is_dir() and (p.stat().st_mode & 0o7777) == mode:
            self._note("keep", p)
        else:
            self._note("create" if not p.exists() else "update", p)
            if not self.dry_run:
                p.mkdir(parents=True, exist_ok=True)
                os.chmod(p, mode)
        if owner and self.live and not self.dry_run:
            shutil.chown(p, owner, owner)

    def _file(self, absolute: str, content: bytes, mode: int, overwrite: bool = True) -> None:
        p = self.path(absolute)
        if p.is_file():
            same = p.read_bytes() == content
            if (same or not overwrite) and (p.stat().st_mode & 0o7777) == mode:
                self._note("keep", p)
                return
            if not same and not overwrite:  # keep the admin's edits; only fix the mode
                self._note("update", p)
                if not self.dry_run:
                    os.chmod(p, mode)
                return
        self._note("create" if not p.exists() else "update", p)
        if self.dry_run:
            return
        p.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(p, content, fsync=False, mode=mode)

    def _symlink(self, absolute: str, target: str) -> None:
        p = self.path(absolute)
        if p.is_symlink() and os.readlink(p) == target:
            self._note("keep", p)
            return
        self._note("create" if not p.is_symlink() else "update", p)
        if self.dry_run:
            return
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.is_symlink() or p.exists():
            p.unlink()
        os.symlink(target, p)

    # ------------------------------------------------------------------ steps

    def run(self) -> InstallReport:
        if not self.root.is_dir():
            raise ConfigError(f"--root {self.root}: not a directory")
        if self.live and os.geteuid() != 0 and not self.dry_run:
            raise InstallError("installing into / needs root (sudo stereopath device install)")
        self.account()
        self.directories()
        self.configuration()
        self.keys()
        self.virtualenv()
        self.unit()
        return self.report

    def account(self) -> None:
        lay = self.layout
        if self.live:
            self._account_live()
            return
        passwd, group = self.path("/etc/passwd"), self.path("/etc/group")
        users = _read_db(passwd)
        groups = _read_db(group)
        used_ids = {int(f[2]) for f in users.values() if len(f) > 2 and f[2].isdigit()} | \
            {int(f[2]) for f in groups.values() if len(f) > 2 and f[2].isdigit()}
        new_groups = dict(groups)
        for name in lay.groups:
            if name not in new_groups:
                gid = _free_system_id(used_ids)
                used_ids.add(gid)
                new_groups[name] = [name, "x", str(gid), ""]
        if lay.user in users:
            uid, gid = users[lay.user][2], users[lay.user][3]
            new_users = users
        else:
            own = new_groups.get(lay.user)
            num = int(own[2]) if own else _free_system_id(used_ids)
            used_ids.add(num)
            uid = gid = str(num)
            new_users = dict(users)
            new_users[lay.user] = [lay.user, "x", uid, gid, "stereopath capture service", lay.state_dir, lay.nologin]
        if lay.user not in new_groups:
            new_groups[lay.user] = [lay.user, "x", gid, ""]
        for name in lay.groups:
            fields = list(new_groups[name])
            members = [m for m in fields[3].split(",") if m] if len(fields) > 3 else []
            if lay.user not in members:
                members.append(lay.user)
            new_groups[name] = [*fields[:3], ",".join(members)]
        self._file("/etc/passwd", _format_db(new_users), 0o644)
        self._file("/etc/group", _format_db(new_groups), 0o644)

    def _account_live(self) -> None:
        import grp
        import pwd

        lay = self.layout
        for name in lay.groups:
            try:
                grp.getgrnam(name)
                self._note("keep", f"group {name}")
            except KeyError:
                self._run(["groupadd", "--system", name])
        try:
            pwd.getpwnam(lay.user)
            self._note("keep", f"user {lay.user}")
            missing = [g for g in lay.groups if lay.user not in grp.getgrnam(g).gr_mem] if not self.dry_run else []
            if missing:
                self._run(["usermod", "--append", "--groups", ",".join(missing), lay.user])
        except KeyError:
            self._run(["useradd", "--system", "--user-group", "--home-dir", lay.state_dir, "--no-create-home",
                       "--shell", lay.nologin, "--comment", "stereopath capture service",
                       "--groups", ",".join(lay.groups), lay.user])

    def directories(self) -> None:
        lay = self.layout
        self._dir(lay.etc_dir, 0o755)
        self._dir(f"{lay.etc_dir}/clients", 0o755)
        self._dir(lay.state_dir, 0o750, owner=lay.user)
        self._dir(lay.sessions, 0o750, owner=lay.user)
        self._dir(lay.prefix, 0o755)

    def configuration(self) -> None:
        src = self.project_dir / "firmware_cfg" / "device.toml"
        if not src.is_file():
            raise InstallError(f"{src} not found: run the installer from a stereopath source checkout")
        self._file(f"{self.layout.etc_dir}/device.toml", src.read_bytes(), 0o644, overwrite=False)
        self._file(self.layout.modules_load, b"# stereopath: /dev/i2c-N for the MPU-6050 (smbus2)\ni2c-dev\n", 0o644)

    def keys(self) -> None:
        etc = self.path(self.layout.etc_dir)
        public, secret = etc / "server.key", etc / "server.key_secret"
        self.report.device_public_key = public
        if public.exists() != secret.exists():
            raise InstallError(f"{public if public.exists() else secret} exists without its pair: remove it or "
                               "restore the other file (keys are never overwritten)")
        if not public.exists():
            self._note("create", public)
            self._note("create", secret)
            if not self.dry_run:
                from stereopath.device.wire.security import generate_keypair

                generate_keypair(etc, "server")
        else:
            self._note("keep", public)
            self._note("keep", secret)
        for p, mode in ((public, 0o644), (secret, 0o600)):
            if p.exists() and (p.stat().st_mode & 0o7777) != mode:
                self._note("update", p)
                if not self.dry_run:
                    os.chmod(p, mode)
        for key in self.host_keys:  # authorise hosts: their public keys into the clients directory
            from stereopath.device.wire.security import load_public_key

            if not key.name.endswith(".key"):
                raise InstallError(f"--host-key {key}: expected a public key file NAME.key (never a .key_secret)")
            load_public_key(key)  # a readable ZeroMQ certificate
            self._file(f"{self.layout.etc_dir}/clients/{key.name}", key.read_bytes(), 0o644)

    def virtualenv(self) -> None:
        venv = self.path(self.layout.venv)
        if (venv / "pyvenv.cfg").is_file():
            self._note("keep", venv)
        else:
            self._note("create", venv)
            if not self.dry_run:
                self.venv.create(venv)
        if self.live:
            self._note("run", f"pip install {self.project_dir} into {self.layout.venv}")
        if not self.dry_run:
            self.venv.install_project(venv, self.project_dir)
        launcher = venv / "bin" / "stereopath"
        if not self.dry_run and not launcher.exists():
            log.warning("%s is missing: the unit's ExecStart will fail until the package is installed", launcher)

    def unit(self) -> None:
        src = self.project_dir / "systemd" / UNIT_NAME
        if not src.is_file():
            raise InstallError(f"{src} not found: run the installer from a stereopath source checkout")
        unit_path = f"{self.layout.unit_dir}/{UNIT_NAME}"
        self._file(unit_path, src.read_bytes(), 0o644)
        backend = self.configured_backend()
        dropin = self.project_dir / "systemd" / BACKEND_DROPINS[backend]
        if not dropin.is_file():
            raise InstallError(f"{dropin} not found: run the installer from a stereopath source checkout")
        self._file(f"{self.layout.unit_dir}/{UNIT_NAME}.d/backend.conf", dropin.read_bytes(), 0o644)
        if backend == "depthai":
            rule = (f"# stereopath: the service user opens the OAK (USB vendor {OAK_USB_VENDOR}) through libusb\n"
                    f'SUBSYSTEM=="usb", ATTRS{{idVendor}}=="{OAK_USB_VENDOR}", MODE="0660", '
                    f'GROUP="{self.layout.user}"\n')
            before = list(self.report.changed)
            self._file(self.layout.udev_rules, rule.encode(), 0o644)
            if self.live and self.report.changed != before and Path("/run/udev/control").exists():
                self._run(["udevadm", "control", "--reload-rules"])
                self._run(["udevadm", "trigger", "--subsystem-match=usb", f"--attr-match=idVendor={OAK_USB_VENDOR}"])
        self._symlink(f"{self.layout.unit_dir}/multi-user.target.wants/{UNIT_NAME}", unit_path)
        if self.live and Path("/run/systemd/system").is_dir():
            self._run(["systemctl", "daemon-reload"])

    def configured_backend(self) -> str:
        """``source.backend`` the drop-in is written for (the installed device.toml, validated)."""
        if self.backend is not None:
            backend = self.backend
        else:
            from stereopath.device.settings import load_device_config

            cfg = self.path(f"{self.layout.etc_dir}/device.toml")
            if not cfg.is_file():  # dry run on a fresh root: the file that would be installed
                cfg = self.project_dir / "firmware_cfg" / "device.toml"
            backend = load_device_config(cfg).source.backend
        if backend not in BACKEND_DROPINS:
            raise InstallError(f"source.backend = {backend!r}: no device drop-in for it "
                               f"(known: {', '.join(BACKEND_DROPINS)})")
        return backend


def _read_db(path: Path) -> dict[str, list[str]]:
    """``name -> fields`` of a passwd/group style file, in file order (empty when missing)."""
    if not path.is_file():
        return {}
    out: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        if line and not line.startswith("#"):
            fields = line.split(":")
            out[fields[0]] = fields
    return out


def _format_db(entries: dict[str, list[str]]) -> bytes:
    return "".join(":".join(f) + "\n" for f in entries.values()).encode()


def _free_system_id(used: set[int], lo: int = 100, hi: int = 999) -> int:
    """The highest free id in the system range (useradd --system counts down from 999)."""
    for n in range(hi, lo - 1, -1):
        if n not in used:
            return n
    raise InstallError(f"no free system user/group id in {lo}..{hi}")


def install(root: str | Path = "/", **kwargs) -> InstallReport:
    """Run every installation step under ``root`` (see :class:`Installer` for the options)."""
    return Installer(root, **kwargs).run()
