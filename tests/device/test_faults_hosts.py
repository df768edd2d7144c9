"""Issue 15 item 1: two hosts with one key both get every keyframe; a host notices a silent stream."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.wire.security import make_demo_keys
from tests.host.test_streaming_integration import _receiver
from tests.device.test_streaming_support import assert_exactly_once, make_device, small_images, stored_seqs, wait_for

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    return make_demo_keys(tmp_path_factory.mktemp("keys"))


def _poll_all(*rxs):
    for rx in rxs:
        rx.poll(0.01)


def test_two_hosts_with_the_same_key_each_get_every_keyframe(tmp_path, keys):
    dev = make_device(tmp_path, keys, "sessT")
    a = _receiver(dev, keys, tmp_path / "a")
    try:
        for i in range(3):
            assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert wait_for(lambda: len(stored_seqs(tmp_path / "a", "sessT")) == 3, 10, between=lambda: _poll_all(a))
        b = _receiver(dev, keys, tmp_path / "b")  # the same key: a second laptop, or `host live` twice
        try:
            assert wait_for(lambda: len(stored_seqs(tmp_path / "b", "sessT")) == 3, 10,
                            between=lambda: _poll_all(a, b))
            for i in range(3, 8):
                assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
            assert wait_for(lambda: all(len(stored_seqs(tmp_path / d, "sessT")) == 8 for d in ("a", "b")), 15,
                            between=lambda: _poll_all(a, b))
            assert wait_for(lambda: a.live.status is not None and b.live.status is not None, 5,
                            between=lambda: _poll_all(a, b))
            # an acknowledgement is sent after the keyframe is stored: wait for it to reach the device
            assert wait_for(lambda: [p["acked"] for p in dev.stats()["peers"]] == [7, 7], 5,
                            between=lambda: _poll_all(a, b)), dev.stats()["peers"]
        finally:
            b.close()
    finally:
        a.close()
        dev.close()
    assert_exactly_once(tmp_path / "a", "sessT", dev.spool)
    assert_exactly_once(tmp_path / "b", "sessT", dev.spool)


def test_host_notices_a_silent_stream_and_says_hello_again(tmp_path, keys):
    dev = make_device(tmp_path, keys, "sessS")
    rx = _receiver(dev, keys, tmp_path / "out")
    try:
        assert dev.offer_keyframe(0, 0, np.eye(4), *small_images(0))
        assert wait_for(lambda: len(stored_seqs(tmp_path / "out", "sessS")) == 1, 10, between=lambda: rx.poll(0.02))
        dev._server._peers.clear()  # the device forgets this connection (as the old same-key takeover did)
        for i in range(1, 4):
            assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert wait_for(lambda: len(stored_seqs(tmp_path / "out", "sessS")) == 4, 15, between=lambda: rx.poll(0.02))
        assert rx.stats.link.rehellos_silent >= 1
    finally:
        rx.close()
        dev.close()
    assert_exactly_once(tmp_path / "out", "sessS", dev.spool)
