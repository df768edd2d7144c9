"""A stage's independent pieces (stereopath.host.backend.parallel): in order by default, handed to a
spreader when one is installed, results always in the order of the items."""

from __future__ import annotations

import pytest

from stereopath.host.backend.parallel import parallel_map, spread_with


def _scaled(shared: int, item: int) -> int:
    return shared * item


def test_pieces_run_here_in_order_without_a_spreader():
    assert parallel_map(_scaled, 3, [1, 2, 5]) == [3, 6, 15]
    assert parallel_map(_scaled, 3, []) == []


def test_a_spreader_gets_the_pieces_and_its_order_of_work_does_not_matter():
    calls = []

    def backwards(fn, shared, items):  # computes the last piece first, returns in the items' order
        calls.append(len(items))
        return list(reversed([fn(shared, it) for it in reversed(items)]))

    with spread_with(backwards):
        assert parallel_map(_scaled, 2, [1, 2, 3]) == [2, 4, 6]
        assert parallel_map(_scaled, 2, [7]) == [14]  # a single piece is not worth sending
    assert calls == [3]
    assert parallel_map(_scaled, 2, [1, 2]) == [2, 4] and calls == [3]  # the block is over


def test_a_spreader_that_loses_pieces_is_an_error():
    with spread_with(lambda fn, shared, items: [fn(shared, items[0])]):
        with pytest.raises(RuntimeError, match="1 results for 2 pieces"):
            parallel_map(_scaled, 1, [1, 2])


def test_depth_pieces_sent_elsewhere_give_the_same_maps():
    """The map stage's per-keyframe depth (StereoDepth pickled to another process, its matcher made
    again there) gives the same bits as here (the fleet test checks the whole model)."""
    import pickle

    import numpy as np

    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.mapping.depth import DEPTH_PRESETS, StereoDepth

    sess = open_sim(SimConfig(frames=30))
    fr = sess.frame(12)
    sd = StereoDepth(sess.rig, DEPTH_PRESETS["object"])
    here = sd.compute(fr.left, fr.right)  # makes (and caches) an OpenCV matcher, which cannot be pickled
    there = pickle.loads(pickle.dumps(sd)).compute(fr.left, fr.right)
    assert here.depth_m.tobytes() == there.depth_m.tobytes()
    assert np.array_equal(here.disparity_px, there.disparity_px, equal_nan=True)
