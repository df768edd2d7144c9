"""Readers of recorded stereo(-inertial) sequences: EuRoC/ASL (and our sessions), KITTI odometry.

Every reader returns an object with the same interface (see :mod:`device.datasets.base`);
:func:`open_source` picks the reader from a ``scheme:path`` string.  The one writer of our
recording layout is :mod:`device.recorder`; file names live in :mod:`device.datasets.layout`.
"""

from device.datasets.asl import AslSequence, open_asl, open_session
from device.datasets.base import SequenceBase
from device.datasets.kitti import KittiSequence, open_kitti
from device.datasets.source import open_source, parse_spec, register_source

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
