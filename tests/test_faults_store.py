"""Issue 15 faults in the host's keyframe store: a torn index, a full disk."""

from __future__ import annotations

import errno
import logging

import pytest

from stereopath.host.live.store import KeyframeStore, read_index
from tests.test_streaming_unit import _kf


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
