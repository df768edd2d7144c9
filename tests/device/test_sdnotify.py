"""sd_notify without libsystemd: datagrams on path and abstract sockets, watchdog environment."""

from __future__ import annotations

import logging
import os
import socket

import pytest

from stereopath.device.service.sdnotify import Notifier, format_message, socket_address, watchdog_interval_s


def _bound(tmp_path, abstract: bool) -> tuple[socket.socket, str]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if abstract:
        name = f"stereopath-sdnotify-{os.getpid()}-{id(s)}"
        s.bind("\0" + name)
        addr = "@" + name
    else:
        addr = str(tmp_path / "notify")
        s.bind(addr)
    s.settimeout(2.0)
    return s, addr


@pytest.mark.parametrize("abstract", [False, True], ids=["path", "abstract"])
def test_datagrams_arrive_on_path_and_abstract_sockets(tmp_path, abstract):
    sock, addr = _bound(tmp_path, abstract)
    with sock, Notifier.from_env({"NOTIFY_SOCKET": addr}) as n:
        assert n.enabled
        assert n.notify(READY=1, STATUS="capturing\nat 20 fps")
        assert n.notify("WATCHDOG=1")
        assert n.notify(STOPPING=True, EXTEND_TIMEOUT_USEC=None)
        assert sock.recv(4096) == b"READY=1\nSTATUS=capturing at 20 fps"
        assert sock.recv(4096) == b"WATCHDOG=1"
        assert sock.recv(4096) == b"STOPPING=1"


def test_without_notify_socket_everything_is_a_no_op():
    n = Notifier.from_env({})
    assert not n.enabled and n.notify(READY=1) is False
    n.close()


def test_a_vanished_socket_is_logged_once_and_never_raises(tmp_path, caplog):
    n = Notifier(str(tmp_path / "gone"))
    caplog.set_level(logging.WARNING, logger="stereopath.device.service.sdnotify")
    assert n.notify("WATCHDOG=1") is False and n.notify("WATCHDOG=1") is False
    assert len(caplog.records) == 1 and "cannot notify" in caplog.records[0].getMessage()


def test_addresses_and_message_format():
    assert socket_address("@sd") == b"\0sd" and socket_address("/run/systemd/notify") == "/run/systemd/notify"
    with pytest.raises(ValueError):
        socket_address("relative/path")
    assert Notifier("relative").enabled is False
    long = format_message(STATUS="x" * 5000).decode()
    assert len(long) <= len("STATUS=") + 1024 and long.endswith("...")


def test_watchdog_interval_from_the_environment():
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 10.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}) == 2.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, pid=4242) is None  # not ours
    assert watchdog_interval_s({"WATCHDOG_USEC": "abc"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
