"""The one error hierarchy of stereopath.

Every expected failure (bad configuration, a broken calibration file, a sensor
that stopped answering, a malformed packet, a damaged dataset) raises a subclass
of :class:`StereopathError`.  The command line prints these on one line and
exits non-zero; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class StereopathError(Exception):
    """Base class of every error stereopath raises on purpose."""


class ConfigError(StereopathError):
    """A configuration key is unknown, missing, of the wrong type or out of range."""


class CalibrationError(StereopathError):
    """A rig calibration is missing, malformed or physically implausible."""


class CaptureError(StereopathError):
    """A sensor (camera, IMU) could not be opened, stopped answering or answered nonsense."""


class ProtocolError(StereopathError):
    """A wire message could not be decoded or failed validation."""


class DatasetError(StereopathError):
    """A recording or dataset on disk is missing, malformed or cannot be decoded."""


class EstimationError(StereopathError):
    """Motion estimation was asked to do something it cannot (e.g. no frames at all)."""


class ImuMismatchError(EstimationError):
    """The IMU's readings do not fit the camera path (units, scale, axes or T_body_cam0 wrong): not to be used."""
