"""What a reprocessing stage records about itself: its CPU time, its memory and the structures it holds."""

from __future__ import annotations

import platform
import sys
import time
from dataclasses import dataclass

import numpy as np
import pytest

from stereopath.host.reprocess.memory import (
    MB,
    MemoryLedger,
    nbytes,
    process_cpu_s,
    reuse_freed_heap,
)


def test_cpu_time_counts_the_work_done():
    c0 = process_cpu_s()
    a = np.random.default_rng(0).standard_normal((300, 300))
    for _ in range(40):
        a = np.tanh(a @ a.T / 300.0)
    assert process_cpu_s() > c0


@dataclass
class _Held:
    points: np.ndarray
    rows: list


def test_held_structures_are_measured_through_their_containers():
    held = _Held(np.zeros((1000, 3)), [np.zeros(500, np.float32), {"a": np.zeros(250, np.int64)}])
    assert nbytes(np.zeros(10)) == 80
    assert nbytes(held) >= 24_000 + 2_000 + 2_000
    assert nbytes(held) < 24_000 + 2_000 + 2_000 + 4_096  # the containers add little


def test_the_ledger_keeps_each_structures_largest_size_and_the_stage_peak():
    led = MemoryLedger()
    led.start()
    big = np.ones(int(64 * MB) // 8)  # 64 MB touched: the stage's peak rises by about that much
    led.note("tracks", big.nbytes)
    led.note("tracks", 10)
    s = led.summary()
    assert s["tracks_mb"] == pytest.approx(64.0)
    assert s["peak_rss_mb"] >= s["start_rss_mb"] + 60 and s["peak_rss_mb"] >= s["rss_mb"] > 0
    del big
    led.start()  # the next stage: the last one's structures forgotten, its memory handed back
    s2 = led.summary()
    assert "tracks_mb" not in s2 and s2["peak_rss_mb"] < s["peak_rss_mb"] - 30  # a peak of its own


def test_the_ledger_sums_the_cpu_time_of_named_steps():
    led = MemoryLedger()
    led.start()

    def spin(seconds: float) -> None:
        c0 = time.process_time()
        while time.process_time() - c0 < seconds:
            pass

    with led.timed("loops"):
        spin(0.05)
    with led.timed("loops"):
        spin(0.05)
    with led.timed("matching"):
        pass
    assert 0.1 <= led.cpu_steps["loops"] < 1.0 and 0 <= led.cpu_steps["matching"] < 0.05
    with pytest.raises(ValueError), led.timed("failing"):  # a step that fails still counts what it used
        spin(0.02)
        raise ValueError
    assert led.cpu_steps["failing"] >= 0.02
    led.start()
    assert led.cpu_steps == {}


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_freed_arrays_stay_in_the_heap_on_glibc():
    assert reuse_freed_heap() is True
