"""The receiver's counters (the ``receiver.json`` format) and its keyframe link's state, without a device."""

from __future__ import annotations

import time

import pytest

from stereopath.host.live.receiver_config import ReceiverConfig
from stereopath.host.live.receiver_link import Link
from stereopath.host.live.receiver_stats import LinkCounters, ReceiverStats
from stereopath.host.live.store import KeyframeStore
from tests.device.test_streaming_support import free_ports

pytestmark = pytest.mark.timeout(30)

LINK_KEYS = ["connects", "disconnects", "auth_failures", "handshake_failures", "hellos", "rehellos_after_stall",
             "acks_unsent", "store_failures", "poses_unsaved", "rehellos_silent"]


def test_receiver_json_keeps_its_keys_and_drops_unknown_counters():
    st = ReceiverStats()
    st.link.connects, st.link.poses_unsaved, st.received.pose, st.received.session = 2, 1, 7, 1
    data = st.to_json()
    assert list(data["link"]) == LINK_KEYS and data["link"]["connects"] == 2
    assert data["received"] == {"pose": 7, "keyframe": 0, "status": 0, "session": 1, "rebase": 0}
    back = ReceiverStats.from_json({**data, "link": {**data["link"], "a_future_counter": 9},
                                    "received": {**data["received"], "ping": 3}})
    assert back.link == st.link and back.received == st.received and back.received.total() == 8


def test_counters_that_are_not_an_object_are_refused():
    with pytest.raises(AttributeError):  # the receiver then starts fresh counters (and says so)
        ReceiverStats.from_json({"link": [1, 2]})


def test_link_quality_follows_connection_refusals_and_traffic(tmp_path):
    pport, kport = free_ports(2)  # nothing listens there: the link stays unconnected
    cfg = ReceiverConfig(f"tcp://127.0.0.1:{pport}", f"tcp://127.0.0.1:{kport}", insecure=True, fsync=False)
    store = KeyframeStore(tmp_path, fsync=False)
    failures: list[str] = []
    link = Link(cfg, None, store, LinkCounters(), lambda what, exc: failures.append(what))
    try:
        now = time.monotonic()
        assert not link.wait(0.0) and not link.connected
        assert link.quality(now, None, 0.0) == "waiting"
        assert link.quality(now, now, 1.0) == "lost"  # traffic without a keyframe connection
        link.counters.auth_failures += 1
        assert link.quality(now, now, 1.0) == "refused"
        link.check(now + 3600.0, None)  # not connected: no hello, no store read
        assert link.counters.hellos == 0 and link.counters.rehellos_silent == 0 and not failures
    finally:
        link.close()
        store.close()
