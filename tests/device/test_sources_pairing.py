"""FramePairer: pairing by timestamp never crosses exposures; drops are counted; thread-safe."""

from __future__ import annotations

import random
import threading
from collections import Counter

import pytest

from stereopath.device.capture.pairing import LEFT, RIGHT, FramePairer

pytestmark = pytest.mark.timeout(30)
P = 10_000_000  # 10 ms frame period


def make(out_maxlen=64):
    counts = Counter()

    def count(**kw):
        counts.update(kw)

    return FramePairer(500_000, count, maxlen=8, out_maxlen=out_maxlen), counts


def drain(p):
    out = []
    while (g := p.get(0.0)) is not None:
        out.append(g)
    return out


def test_lost_partner_drops_the_unpaired_frame_only():
    p, c = make()
    for k in range(10):
        if k != 4:
            p.push(LEFT, k * P, ("L", k))
        if k != 7:
            p.push(RIGHT, k * P + 200_000, ("R", k))
    pairs = drain(p)
    assert [(l[1], r[1]) for l, r, _ in pairs] == [(k, k) for k in range(10) if k not in (4, 7)]
    assert all(skew == 200_000 for _, _, skew in pairs)
    assert c["dropped_unpaired"] == 2 and c["paired"] == 8


def test_skew_beyond_tolerance_never_pairs_neighbours():
    p, c = make()
    for k in range(6):
        p.push(LEFT, k * P, k)
        p.push(RIGHT, k * P + 3_000_000, k)   # 3 ms apart, tolerance 0.5 ms
    assert drain(p) == [] and c["paired"] == 0
    assert c["dropped_unpaired"] >= 5


def test_out_of_order_and_overflow_are_counted():
    p, c = make()
    p.push(LEFT, 5 * P, 5)
    p.push(LEFT, 4 * P, 4)          # older than the queue tail: refused
    assert c["dropped_unpaired"] == 1
    for k in range(6, 20):          # right camera silent: the left queue stays bounded
        p.push(LEFT, k * P, k)
    assert p.pending()[0] == 8 and c["dropped_overflow"] == 15 - 8


def test_two_producer_threads_with_random_losses():
    p, c = make(out_maxlen=1000)  # the consumer may lag: keep every pair to check them all
    rng = random.Random(1)
    lost = {LEFT: {k for k in range(400) if rng.random() < 0.05}, RIGHT: {k for k in range(400) if rng.random() < 0.05}}
    got = []
    done = threading.Event()

    progress = [0, 0]
    cond = threading.Condition()

    def producer(side):  # like two cameras: neither runs more than 3 frames ahead of the other
        for k in range(400):
            with cond:
                cond.wait_for(lambda: progress[1 - side] >= k - 3, timeout=5)
            if k not in lost[side]:
                p.push(side, k * P + (137_000 if side else 0), k)
            with cond:
                progress[side] = k + 1
                cond.notify_all()

    def consumer():
        while not done.is_set() or p.pending()[2]:
            g = p.get(0.01)
            if g is not None:
                got.append(g)

    threads = [threading.Thread(target=producer, args=(s,)) for s in (LEFT, RIGHT)]
    cons = threading.Thread(target=consumer)
    cons.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    done.set()
    cons.join(10)
    assert all(l == r for l, r, _ in got)
    expected = set(range(400)) - lost[LEFT] - lost[RIGHT]
    # the last frames of one side may still wait for a partner; nothing else is missing
    assert {l for l, _, _ in got} >= expected - set(range(396, 400))
    assert c["paired"] == len(got) and c["dropped_overflow"] == 0


def test_close_wakes_a_waiting_consumer():
    p, _ = make()
    res = []
    t = threading.Thread(target=lambda: res.append(p.get(5.0)))
    t.start()
    p.close()
    t.join(2.0)
    assert not t.is_alive() and res == [None]
