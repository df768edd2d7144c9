"""`--map-preset auto`: the dense model's preset chosen from the keyframes' stereo depth."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.host.mapping.auto_preset import OBJECT_EXTENT_M, choose_from_survey
from stereopath.host.mapping.mapper import MAP_PRESETS, PRESET_CHOICES

MAX = {k: MAP_PRESETS[k].depth.max_depth_m for k in ("object", "room", "large_room")}


def _plane(rng, n, centre, half_extent, depth):
    X = np.asarray(centre) + rng.uniform(-1, 1, (n, 3)) * half_extent
    return np.full(n, depth) + rng.normal(0, 0.05, n), X


def test_choice_from_depths_and_extents():
    rng = np.random.default_rng(0)
    obj = _plane(rng, 3000, (0, 0, 0), (0.3, 0.3, 0.2), 0.8)  # a thing 0.6 m across at 0.8 m
    wall = _plane(rng, 2000, (0, 3, 1), (2, 0.01, 1.2), 3.2)  # the far wall behind it
    c = choose_from_survey(np.r_[obj[0], wall[0]], np.vstack([obj[1], wall[1]]), MAX, 6)
    assert c.preset == "object" and "object range" in c.reason and max(c.near_extent_m) < OBJECT_EXTENT_M
    walls = _plane(rng, 5000, (0, 0, 1.3), (2, 2, 1.2), 1.6)  # a room's walls, near but all round
    c = choose_from_survey(*walls, MAX, 6)
    assert c.preset == "room" and "span" in c.reason
    pallet = _plane(rng, 800, (0, 0.5, 0), (0.4, 0.4, 0.3), 1.2)  # a pallet at the feet, the hall beyond
    hall = _plane(rng, 5000, (0, 12, 4), (10, 0.5, 4), 11.0)
    c = choose_from_survey(np.r_[pallet[0], hall[0]], np.vstack([pallet[1], hall[1]]), MAX, 6)
    assert c.preset == "large_room" and c.near_share < 0.3
    c = choose_from_survey(np.zeros(0), np.zeros((0, 3)), MAX, 6)
    assert c.preset == "object" and "no valid stereo depth" in c.reason
    assert PRESET_CHOICES[0] == "auto" and set(PRESET_CHOICES[1:]) == set(MAP_PRESETS)


def test_command_lines_offer_the_mapper_presets():
    from stereopath.host.commands.map import MAP_PRESET_CHOICES

    assert MAP_PRESET_CHOICES == PRESET_CHOICES


@pytest.mark.parametrize("trajectory, expected", [("arc", "object"), ("loop", "room")])
def test_simulated_table_top_scan_is_an_object_and_the_loop_a_room(trajectory, expected):
    """The default simulated scan (a table top, the walls 3 m behind) and the room-facing loop."""
    from stereopath.device.formats.source import open_source
    from stereopath.host.mapping.mapper import auto_config
    from stereopath.host.mapping.inputs import keyframes_from_sequence

    seq = open_source("sim:0", trajectory=trajectory)  # frames are rendered only where surveyed
    cfg, choice = auto_config(seq.rig, lambda sel: keyframes_from_sequence(seq, seq.groundtruth, sel).keyframes)
    assert choice["preset"] == cfg.preset == expected, choice
    assert choice["asked"] == "auto" and choice["keyframes_surveyed"] == 6


@pytest.mark.realdata
def test_euroc_vicon_room_frames_are_a_room(data_dir):
    from stereopath.device.formats.source import open_source
    from stereopath.host.mapping.mapper import auto_config
    from stereopath.host.mapping.inputs import keyframes_from_sequence

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head' / 'mav0'}")
    cfg, choice = auto_config(seq.rig, lambda sel: keyframes_from_sequence(seq, seq.groundtruth, sel).keyframes)
    assert choice["preset"] == "room", choice
