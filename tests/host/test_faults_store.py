"""Issue 15 faults in the host's keyframe store: a torn index, a full disk."""

from __future__ import annotations

import logging

import pytest

from stereopath.host.live.store import KeyframeStore, read_index
from tests.device.test_streaming_unit import _kf


def _store_with(tmp_path, n):
    store = KeyframeStore(tmp_path, fsync=False)
    for seq in range(n):
        store.put(*_kf("s", seq))
    store.close()
    return tmp_path / "s" / "keyframes" / "index.csv"


@pytest.mark.parametrize("cut", [1, 20, 40])
def test_torn_index_recovers_prefix_and_reappends(tmp_path, caplog, cut):
    index = _store_with(tmp_path, 3)
    data = index.read_bytes()
    index.write_bytes(data[:-cut])  # a power cut during the last append
    caplog.set_level(logging.WARNING)
    rows = read_index(tmp_path / "s")
    assert [r["seq"] for r in rows] == [0, 1]
    assert "torn or malformed" in caplog.text
    caplog.clear()
    store = KeyframeStore(tmp_path, fsync=False)
    sess = store.session("s")
    assert sess.acked_seq == 2
    assert sum("torn or malformed" in r.message for r in caplog.records) == 1
    store.put(*_kf("s", 3))
    store.close()
    caplog.clear()
    assert [r["seq"] for r in read_index(tmp_path / "s")] == [0, 1, 2, 3]
    assert "torn" not in caplog.text
    # and a second restart is quiet
    KeyframeStore(tmp_path, fsync=False).session("s")
    assert "torn" not in caplog.text and "rebuilding" not in caplog.text


def test_index_with_garbage_line_keeps_prefix(tmp_path):
    index = _store_with(tmp_path, 2)
    with index.open("ab") as fh:
        fh.write(b"\x00\x00\x00garbage,,\n")
    assert [r["seq"] for r in read_index(tmp_path / "s")] == [0, 1]
    store = KeyframeStore(tmp_path, fsync=False)
    assert store.session("s").acked_seq == 1
    store.close()
    assert [r["seq"] for r in read_index(tmp_path / "s")] == [0, 1]


# item 3: host disk full ---------------------------------------------------------------------------

def test_host_disk_full_keeps_keyframes_unacked_until_space_returns(tmp_path, monkeypatch, caplog):
    import numpy as np

    from stereopath.host.live import receiver as receiver_mod
    from stereopath.host.live import store as store_mod
    from stereopath.device.wire.security import make_demo_keys
    from tests.host.test_streaming_integration import _receiver
    from tests.device.test_streaming_support import assert_exactly_once, make_device, small_images, wait_for, \
        write_or_enospc

    full = {"on": True}
    monkeypatch.setattr(store_mod, "write_atomic", write_or_enospc(store_mod.write_atomic, full))
    monkeypatch.setattr(receiver_mod, "write_json_atomic", write_or_enospc(receiver_mod.write_json_atomic, full))
    keys = make_demo_keys(tmp_path / "keys")
    dev = make_device(tmp_path, keys, "sessF")
    out = tmp_path / "out"
    rx = _receiver(dev, keys, out, stats_interval_s=0.1)
    caplog.set_level(logging.INFO)
    try:
        for i in range(6):
            assert dev.offer_keyframe(i, i * 50_000_000, np.eye(4), *small_images(i))
        assert dev.wait_spooled(6, 10)
        assert wait_for(lambda: rx.stats.link.store_failures >= 2, 10, between=lambda: rx.poll(0.02))
        for _ in range(20):
            rx.poll(0.02)
        assert not list(out.rglob("kf_*"))
        assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
        assert rx.storage_error is not None and "No space left" in rx.storage_error
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR and "cannot store" in r.getMessage()]
        assert len(errors) == 1  # one clear line, not one per keyframe
        assert dev.stats()["acks"] == 0  # nothing stored, nothing acknowledged
        full["on"] = False  # space returns: the stall check says hello again and the device resends
        assert wait_for(lambda: rx.store.session("sessF").acked_seq == 5, 15, between=lambda: rx.poll(0.02))
        assert rx.storage_error is None
    finally:
        rx.close()
        dev.close()
    assert_exactly_once(out, "sessF", dev.spool)


def test_a_keyframe_refused_by_a_full_host_disk_is_asked_for_again_as_soon_as_storing_works(tmp_path, monkeypatch):
    """Keyframe 2 hits a full disk, 3 and later are stored: the host says hello at once (not after a stall of
    stall_timeout_s, which the device's end-of-run drain would not wait for) and holds all of them."""
    import errno

    import numpy as np

    from stereopath.host.live import store as store_mod
    from stereopath.host.live.receiver import Receiver
    from stereopath.host.live.receiver_config import ReceiverConfig, SocketTiming
    from tests.device.test_streaming_support import assert_exactly_once, make_device, small_images, wait_for

    real = store_mod.write_atomic
    refused = []

    def once_full(path, data, *a, **k):
        if "00000002" in str(path) and not refused:
            refused.append(path)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data, *a, **k)

    monkeypatch.setattr(store_mod, "write_atomic", once_full)
    dev = make_device(tmp_path, None, "sessH")
    out = tmp_path / "out"
    rx = Receiver(ReceiverConfig(dev.pose_endpoint, dev.keyframe_endpoint, insecure=True, fsync=False,
                                 sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500,
                                                      reconnect_ivl_ms=50, reconnect_ivl_max_ms=400),
                                 stall_timeout_s=60.0), out)
    try:
        for i in range(6):
            assert dev.offer_keyframe(i, i * 50_000_000, np.eye(4), *small_images(i))
        assert dev.wait_spooled(6, 10)
        assert wait_for(lambda: rx.store.session("sessH").acked_seq == 5, 10, between=lambda: rx.poll(0.02))
        assert refused and rx.stats.link.hellos >= 2 and rx.stats.link.rehellos_after_stall == 0
    finally:
        rx.close()
        dev.close()
    assert_exactly_once(out, "sessH", dev.spool)


@pytest.mark.slow
def test_a_keyframe_that_keeps_failing_does_not_set_off_a_resend_loop(tmp_path, monkeypatch):
    """Keyframe 2 never fits: the duplicates the device resends after each hello are not taken as the disk
    working again, and hellos for the refused keyframe come at most once a second (there were hundreds)."""
    import errno
    import time

    import numpy as np

    from stereopath.host.live.receiver_link import RECOVERY_HELLO_MIN_S
    from stereopath.host.live import store as store_mod
    from stereopath.host.live.receiver import Receiver
    from stereopath.host.live.receiver_config import ReceiverConfig, SocketTiming
    from tests.device.test_streaming_support import make_device, small_images, wait_for

    real = store_mod.write_atomic

    def never_2(path, data, *a, **k):
        if "00000002" in str(path):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data, *a, **k)

    monkeypatch.setattr(store_mod, "write_atomic", never_2)
    dev = make_device(tmp_path, None, "sessL")
    rx = Receiver(ReceiverConfig(dev.pose_endpoint, dev.keyframe_endpoint, insecure=True, fsync=False,
                                 sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500,
                                                      reconnect_ivl_ms=50, reconnect_ivl_max_ms=400),
                                 stall_timeout_s=60.0), tmp_path / "out")
    try:
        for i in range(6):
            assert dev.offer_keyframe(i, i * 50_000_000, np.eye(4), *small_images(i))
        assert dev.wait_spooled(6, 10)
        start = time.monotonic()
        wait_for(lambda: False, 3.0, between=lambda: rx.poll(0.02))
        elapsed = time.monotonic() - start
        assert rx.store.session("sessL").acked_seq == 1
        assert rx.stats.link.hellos <= 2 + elapsed / RECOVERY_HELLO_MIN_S
        assert dev.stats()["keyframes_resent"] <= 4 * (1 + elapsed / RECOVERY_HELLO_MIN_S)
    finally:
        rx.close()
        dev.close()
