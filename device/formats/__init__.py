"""Readers of recorded stereo(-inertial) sequences: EuRoC/ASL (and our sessions), KITTI odometry.

Every reader returns an object with the same interface (see :mod:`stereopath.device.formats.sequence`);
:func:`open_source` picks the reader from a ``scheme:path`` string.  The one writer of our
recording layout is :mod:`stereopath.device.formats.recorder`; file names live in :mod:`stereopath.device.formats.layout`.
"""

from stereopath.device.formats.asl import AslSequence, open_asl, open_session
from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.formats.kitti import KittiSequence, open_kitti
from stereopath.device.formats.source import open_source, parse_spec, register_source

__all__ = [
    "AslSequence",
    "KittiSequence",
    "SequenceBase",
    "open_asl",
    "open_kitti",
    "open_session",
    "open_source",
    "parse_spec",
    "register_source",
]
