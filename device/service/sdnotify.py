"""systemd service notifications (``sd_notify``) written directly on ``$NOTIFY_SOCKET``.

systemd passes a ``Type=notify`` service the address of a datagram socket in the
environment variable ``NOTIFY_SOCKET``: a file-system path (``/run/systemd/notify``) or an
abstract-namespace name written with a leading ``@``.  A notification is one datagram of
newline-separated ``KEY=VALUE`` assignments (``READY=1``, ``WATCHDOG=1``, ``STATUS=...``,
``STOPPING=1``, ``RELOADING=1``, ``EXTEND_TIMEOUT_USEC=...``); see sd_notify(3).  No
dependency on libsystemd: this is an ``AF_UNIX``/``SOCK_DGRAM`` ``sendto``.

Without ``NOTIFY_SOCKET`` (run by hand, in tests without a socket) every call is a no-op.
Send errors are logged once and never raised: the service must not fail because its
supervisor is gone.

``watchdog_interval_s()`` reads ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``, which must be
ours) like ``sd_watchdog_enabled(3)``; the service pings every half of it.

Example::

    notifier = Notifier.from_env()
    notifier.notify(READY=1, STATUS="capturing")
    notifier.notify(WATCHDOG=1)
    notifier.close()
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from typing import Mapping

log = logging.getLogger(__name__)

MAX_STATUS_CHARS = 1024


def socket_address(value: str) -> str | bytes:
    """The ``sendto`` address of a ``NOTIFY_SOCKET`` value ('@name' = abstract namespace)."""
    if not value:
        raise ValueError("empty NOTIFY_SOCKET")
    if value[0] == "@":
        return b"\0" + value[1:].encode()
    if value[0] != "/":
        raise ValueError(f"NOTIFY_SOCKET {value!r} is neither an absolute path nor an @abstract name")
    return value


def format_message(*lines: str, **fields: object) -> bytes:
    """Encode assignments as one datagram; newlines inside values are replaced by spaces."""
    out = list(lines)
    for key, value in fields.items():
        if value is None:
            continue
        if isinstance(value, bool):
            value = int(value)
        text = " ".join(str(value).split("\n"))
        if key == "STATUS" and len(text) > MAX_STATUS_CHARS:
            text = text[: MAX_STATUS_CHARS - 3] + "..."
        out.append(f"{key}={text}")
    return "\n".join(out).encode("utf-8", "replace")


class Notifier:
    """Sends notifications to one socket address (``None`` = disabled, every call a no-op)."""

    def __init__(self, address: str | None) -> None:
        self.address_text = address or None
        self._addr: str | bytes | None = None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._warned = False
        self.sent: list[bytes] = []  # the last few datagrams, for diagnostics
        if address:
            try:
                self._addr = socket_address(address)
            except ValueError as exc:
                log.warning("service notifications disabled: %s", exc)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "Notifier":
        env = os.environ if environ is None else environ
        return cls(env.get("NOTIFY_SOCKET") or None)

    @property
    def enabled(self) -> bool:
        return self._addr is not None

    def notify(self, *lines: str, **fields: object) -> bool:
        """Send one datagram (``notify("READY=1")`` or ``notify(READY=1, STATUS="...")``).

        Returns True when the datagram was handed to the kernel.
        """
        if self._addr is None:
            return False
        data = format_message(*lines, **fields)
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.sendto(data, self._addr)
            except OSError as exc:
                if not self._warned:
                    log.warning("cannot notify the service manager at %s: %s", self.address_text, exc)
                    self._warned = True
                return False
            self.sent.append(data)
            del self.sent[:-32]
        return True

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> "Notifier":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def watchdog_interval_s(environ: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """The watchdog timeout in seconds when systemd expects pings from this process, else None."""
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring WATCHDOG_USEC=%r (not an integer)", usec)
        return None
    if value <= 0:
        return None
    wpid = env.get("WATCHDOG_PID")
    if wpid:
        try:
            if int(wpid) != (os.getpid() if pid is None else pid):
                return None
        except ValueError:
            return None
    return value / 1e6
