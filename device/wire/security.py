"""CURVE keys, the ZAP authenticator and the loopback rule for plain TCP.

Key files are ZeroMQ certificates (``zmq.auth.create_certificates``): ``NAME.key`` holds the
public key, ``NAME.key_secret`` both keys.  The device holds its own secret key and a directory
of authorised host public keys; a host holds its own secret key and the device's public key.
Layout used by :func:`make_demo_keys` (and by the demo)::

    ROOT/device/device.key, device.key_secret    the device's key pair
    ROOT/device/clients/host.key                 hosts allowed to connect
    ROOT/host/host.key, host.key_secret          the host's key pair
    ROOT/host/device.key                         the device's public key

Without CURVE (``insecure``), endpoints must be loopback addresses: :func:`check_loopback_endpoint`.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import re
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stereopath.device.errors import ConfigError

if TYPE_CHECKING:
    import zmq
    from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger(__name__)

KEY_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def require_curve() -> None:
    """Raise :class:`ConfigError` if this libzmq was built without CURVE."""
    import zmq

    if not zmq.has("curve"):
        raise ConfigError(f"libzmq {zmq.zmq_version()} has no CURVE support; install a pyzmq wheel "
                          "built with libsodium, or run with --insecure on loopback only")


def generate_keypair(directory: str | Path, name: str, overwrite: bool = False) -> tuple[Path, Path]:
    """Write ``DIR/NAME.key`` (public) and ``DIR/NAME.key_secret`` (mode 0600); return both paths."""
    import zmq.auth

    require_curve()
    if not KEY_NAME_RE.match(name):
        raise ConfigError(f"key name {name!r} must match {KEY_NAME_RE.pattern}")
    from stereopath.device.formats.fileio import check_out_folder

    d = Path(directory)
    check_out_folder(d, option="key directory")  # a file in the way, or no write permission: ConfigError
    d.mkdir(parents=True, exist_ok=True)
    public, secret = d / f"{name}.key", d / f"{name}.key_secret"
    for f in (public, secret):
        if f.exists() and not f.is_file():
            raise ConfigError(f"{f} exists and is not a key file (refusing to replace it)")
    if not overwrite and (public.exists() or secret.exists()):
        raise ConfigError(f"key files for {name!r} already exist in {d} (refusing to overwrite)")
    import tempfile

    # the library writes with the process umask: let it write into a private (0700) folder, then
    # create the final secret file with mode 0600 from the start (never readable by others)
    with tempfile.TemporaryDirectory(prefix=".keys-", dir=d) as tmp:
        pub_tmp, sec_tmp = zmq.auth.create_certificates(tmp, name)
        for src, dst, mode in ((sec_tmp, secret, 0o600), (pub_tmp, public, 0o644)):
            data = Path(src).read_bytes()
            if overwrite:
                dst.unlink(missing_ok=True)
            fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
            finally:
                os.close(fd)
    return public, secret


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def _load_certificate(p: Path, what: str) -> tuple[bytes, bytes | None]:
    """``(public, secret or None)`` from a ZeroMQ certificate file; ConfigError names the file."""
    import zmq.auth

    try:
        mode = p.stat().st_mode  # (of the file a link points to)
    except FileNotFoundError:
        raise ConfigError(f"CURVE {what} key file not found: {p}") from None
    except OSError as exc:
        raise ConfigError(f"CURVE {what} key file {p}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):  # never opened: reading a FIFO would block the start for good
        raise ConfigError(f"CURVE {what} key file {p} is {_file_kind(mode)}, not a regular file")
    try:
        return zmq.auth.load_certificate(str(p))
    except (ValueError, OSError) as exc:
        raise ConfigError(f"{p}: not a ZeroMQ certificate: {exc}") from None


def load_secret_keypair(path: str | Path) -> tuple[bytes, bytes]:
    """``(public, secret)`` Z85 keys from a ``*.key_secret`` file."""
    p = Path(path)
    public, secret = _load_certificate(p, "secret")
    if not secret:
        raise ConfigError(f"{p} holds no secret key (is it the public .key file?)")
    check_secret_mode(p)
    return public, secret


def check_secret_mode(path: str | Path) -> None:
    """Refuse a secret key file that group or others may read or write (OpenSSH refuses such a private key).

    A symbolic link is judged by the file it points to: that file's mode is what guards the key."""
    p = Path(path)
    try:
        target = p.resolve(strict=True)
        mode = target.stat().st_mode
    except OSError as exc:
        raise ConfigError(f"{p}: cannot check the secret key's permissions: {exc.strerror or exc}") from None
    if mode & 0o077:
        via = "" if target == p.absolute() else f" (through the link {p})"
        raise ConfigError(f"secret key {target}{via} is accessible by group/others (mode {stat.S_IMODE(mode):04o}); "
                          f"a secret key must be private: chmod 600 {_quoted(target)}")


def _quoted(path: Path) -> str:
    import shlex

    return shlex.quote(str(path))


def check_clients_dir_mode(clients_dir: str | Path) -> None:
    """Refuse an authorised-hosts folder, or a host key in it, that group or others may write: whoever can
    write there authorises a host at the next start (OpenSSH refuses such an authorized_keys)."""
    d = Path(clients_dir)
    items = [d] + sorted(d.glob("*.key"))
    for item in items:
        target = item.resolve()
        mode = target.stat().st_mode
        if mode & (stat.S_IWGRP | stat.S_IWOTH):
            what = "authorised host key folder" if item == d else "authorised host key"
            raise ConfigError(f"{what} {target} is writable by group/others (mode {stat.S_IMODE(mode):04o}): "
                              f"anyone who can write there could authorise a host; chmod go-w {_quoted(target)}")


def load_public_key(path: str | Path) -> bytes:
    """Z85 public key from a ``*.key`` (or ``*.key_secret``) file."""
    return _load_certificate(Path(path), "public")[0]


def authorized_keys(clients_dir: str | Path) -> list[Path]:
    """The ``*.key`` files of the authorised-hosts directory (at least one, else ConfigError)."""
    d = Path(clients_dir)
    if not d.is_dir():
        raise ConfigError(f"authorised host key directory not found: {d}")
    check_clients_dir_mode(d)
    keys = sorted(d.glob("*.key"))
    if not keys:
        raise ConfigError(f"no authorised host keys (*.key) in {d}: no host could connect")
    for k in keys:
        load_public_key(k)  # fail early on a damaged file
    return keys


class _ZapLog:
    """The authenticator's logger, with refused clients raised to a warning (once per key and address).

    pyzmq's authenticator reports a refused key only at debug level; a device that silently turns
    hosts away is hard to diagnose.  Later refusals of the same key are logged at debug level and
    counted in :attr:`refused`.
    """

    MAX_REMEMBERED = 256

    def __init__(self, logger: logging.Logger) -> None:
        self._log = logger
        self._address = ""
        self._warned: set[tuple[str, str]] = set()
        self.refused = 0

    def debug(self, msg: str, *args: object, **kw: object) -> None:
        if msg.startswith("version:") and len(args) >= 4:
            self._address = str(args[3])
        elif "CURVE" in msg and (msg.startswith("DENIED") or (args and args[0] == "DENIED")):
            self.refused += 1
            key = str(args[-1]) if args else "?"
            if key.startswith("b'"):
                key = key[2:-1]
            ident = (key, self._address)
            if ident not in self._warned and len(self._warned) < self.MAX_REMEMBERED:
                self._warned.add(ident)
                self._log.warning("refused a client from %s: CURVE key %s is not in the authorised hosts "
                                  "folder", self._address or "?", key)
                return
        self._log.debug(msg, *args, **kw)

    def __getattr__(self, name: str) -> Any:  # info, warning, error, ...
        return getattr(self._log, name)


def start_authenticator(ctx: zmq.Context, clients_dir: str | Path) -> ThreadAuthenticator:
    """Start a ZAP authenticator on ``ctx`` admitting only the CURVE keys in ``clients_dir``.

    Refused clients are logged as warnings (see :class:`_ZapLog`)."""
    from zmq.auth.thread import ThreadAuthenticator

    keys = authorized_keys(clients_dir)
    auth = ThreadAuthenticator(ctx, log=_ZapLog(logging.getLogger(__name__ + ".zap")))
    auth.start()
    auth.configure_curve(domain="*", location=str(Path(clients_dir)))
    log.info("CURVE: %d authorised host key(s) in %s", len(keys), clients_dir)
    return auth


def load_host_keys(keys_dir: str | Path, device_key: str | Path | None = None) -> tuple[bytes, bytes, bytes]:
    """``(host_public, host_secret, device_public)`` from a host key directory.

    The directory holds exactly one ``*.key_secret`` (the host's pair) and, unless
    ``device_key`` names another file, the device's public key as ``device.key``.
    """
    d = Path(keys_dir)
    if not d.is_dir():
        raise ConfigError(f"host key directory not found: {d}")
    secrets_ = sorted(d.glob("*.key_secret"))
    if len(secrets_) != 1:
        raise ConfigError(f"{d} must hold exactly one *.key_secret (the host's key pair), found "
                          f"{[s.name for s in secrets_]}")
    pub, sec = load_secret_keypair(secrets_[0])
    server = load_public_key(Path(device_key) if device_key else d / "device.key")
    return pub, sec, server


@dataclass(frozen=True)
class DemoKeys:
    """Paths of a freshly generated device/host key set (see the module docstring)."""

    root: Path
    device_secret: Path
    clients_dir: Path
    host_keys_dir: Path
    host_secret: Path
    device_public: Path


def make_demo_keys(root: str | Path, host_name: str = "host") -> DemoKeys:
    """Generate a device key pair and one authorised host key pair under ``root``."""
    r = Path(root)
    dev_pub, dev_sec = generate_keypair(r / "device", "device", overwrite=True)
    host_pub, host_sec = generate_keypair(r / "host", host_name, overwrite=True)
    clients = r / "device" / "clients"
    clients.mkdir(mode=0o755, parents=True, exist_ok=True)  # never group-writable, whatever the umask
    shutil.copy(host_pub, clients / host_pub.name)
    shutil.copy(dev_pub, r / "host" / "device.key")
    return DemoKeys(r, dev_sec, clients, r / "host", host_sec, r / "host" / "device.key")


_ENDPOINT_RE = re.compile(r"^(?P<scheme>[a-z]+)://(?P<rest>.+)$")


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """``(scheme, host)`` of a ZeroMQ endpoint (``tcp://HOST:PORT``; IPv6 as ``[::1]``)."""
    m = _ENDPOINT_RE.match(endpoint)
    if not m:
        raise ConfigError(f"endpoint {endpoint!r} is not of the form scheme://address")
    scheme, rest = m.group("scheme"), m.group("rest")
    if scheme != "tcp":
        return scheme, rest
    if ";" in rest:
        raise ConfigError(f"endpoint {endpoint!r}: source-address endpoints are not supported")
    if rest.startswith("["):
        host, sep, _ = rest[1:].partition("]")
        if not sep:
            raise ConfigError(f"endpoint {endpoint!r}: unterminated IPv6 address")
        return scheme, host
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port:
        raise ConfigError(f"endpoint {endpoint!r} must be tcp://HOST:PORT")
    return scheme, host


def is_loopback_host(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_loopback_endpoint(endpoint: str) -> None:
    """Refuse (ConfigError) any endpoint that could reach the network without CURVE.

    Allowed: ``tcp://`` with a loopback address (127.0.0.0/8, ::1, localhost), ``ipc://`` and
    ``inproc://``.  Wildcards (``*``, ``0.0.0.0``), interface names and other hosts are refused.
    """
    scheme, host = endpoint_host(endpoint)
    if scheme in ("ipc", "inproc"):
        return
    if scheme != "tcp" or not is_loopback_host(host):
        raise ConfigError(f"insecure (no CURVE) endpoint {endpoint!r} refused: without encryption only "
                          "loopback addresses (127.0.0.1, ::1, localhost) are allowed")
