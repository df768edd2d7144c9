"""The wire's message types and identifiers: what device and host exchange, with its bounds.

See :mod:`stereopath.device.wire.protocol` for the encoding; this module holds the shapes
(:class:`Pose`, :class:`Keyframe`, :class:`Status` with :class:`DeviceHealth`, :class:`SessionInfo`, :class:`Hello`,
:class:`Ack`, :class:`Credit`, :class:`WorldRebase`), the limits applied to untrusted bytes and the session-id rules.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import secrets
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.errors import ProtocolError

if TYPE_CHECKING:
    from stereopath.device.core.rig import Rig

PROTOCOL_VERSION = 1
POSE_MAX_BYTES = 128

TRACKING_STATES = ("ok", "imu_only", "lost")
IMAGE_ENCODINGS = ("jpg", "png", "raw")
RAW_DTYPES = ("|u1", "<u2")  # allow-list for raw pixels (and the decoded dtype of PNG/JPEG)
MAX_IMAGE_SIDE = 8192
IMAGE_CHANNELS = (1, 3)

SESSION_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,30}$")
RIG_NAME_RE = re.compile(r"^[A-Za-z0-9_.+-]{1,64}$")
RIG_HASH_RE = re.compile(r"^[0-9a-f]{8,64}$")
RECORDER_STATE_RE = re.compile(r"^[a-z][a-z0-9_]{0,23}$")

U32 = 2**32 - 1
I63 = 2**63 - 1
MAX_CREDIT = 1024
MAX_POSITION_M = 1.0e6


class DecodeError(ProtocolError):
    """A received message was rejected; ``reason`` is a short counter key (e.g. ``"malformed"``)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class Limits:
    """Bounds applied to untrusted bytes before and while unpacking."""

    max_message_bytes: int
    max_bin_len: int = 0
    max_str_len: int = 64
    max_array_len: int = 8
    max_map_len: int = 20


POSE_LIMITS = Limits(max_message_bytes=256)
CONTROL_LIMITS = Limits(max_message_bytes=512)
KEYFRAME_LIMITS = Limits(max_message_bytes=64 * 2**20, max_bin_len=32 * 2**20)
# a session message carries the rig calibration: up to 14 distortion coefficients and a free rig name
SESSION_LIMITS = Limits(max_message_bytes=16384, max_array_len=16, max_str_len=256)


# --------------------------------------------------------------------------- message types


@dataclass(frozen=True)
class Pose:
    """Live camera pose ``T_world_cam`` as position (m) and unit quaternion (x, y, z, w)."""

    session_id: str
    seq: int
    t_ns: int
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    tracking: str = "ok"
    inliers: int = 0
    keyframe: bool = False

    @property
    def T_world_cam(self) -> np.ndarray:
        return pose_matrix(self.position_m, self.quat_xyzw)


@dataclass(frozen=True)
class EncodedImage:
    """One image as sent: ``encoding`` jpg/png/raw, the payload, its (h, w[, c]) shape and dtype."""

    encoding: str
    data: bytes
    shape: tuple[int, ...]
    dtype: str = "|u1"


@dataclass(frozen=True)
class Keyframe:
    """A keyframe: pose, both images and the rig calibration reference."""

    session_id: str
    seq: int
    frame_seq: int
    t_ns: int
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    left: EncodedImage
    right: EncodedImage
    rig_name: str
    rig_hash: str

    @property
    def T_world_cam(self) -> np.ndarray:
        return pose_matrix(self.position_m, self.quat_xyzw)


@dataclass(frozen=True)
class SessionInfo:
    """Device -> host, once per session on each connection, before that session's keyframes.

    ``rig`` is the session's calibration in the rig YAML schema
    (:func:`stereopath.device.core.rig.rig_to_dict`; None when the device has none to send), named
    by ``rig_name``/``rig_hash`` exactly as its keyframes name it.  ``keyframes`` is how many
    keyframes the device has spooled of the session (so far, for the live one); ``live`` is False
    for an earlier session whose unacknowledged keyframes the device still holds (a killed run).
    """

    session_id: str
    rig_name: str
    rig_hash: str
    rig: dict[str, Any] | None
    keyframes: int
    live: bool = True


@dataclass(frozen=True)
class _StatusHeader:
    session_id: str
    t_ns: int


@dataclass(frozen=True)
class DeviceHealth:
    """The device health fields, declared once: the service measures them, the status message carries them.

    ``None`` = not measured (the streamer probes CPU, temperature and disk itself then).
    """

    frame_rate_hz: float = 0.0
    imu_rate_hz: float = 0.0
    dropped_frames: int = 0
    imu_gaps: int = 0
    cpu_load_pct: float | None = None
    temperature_c: float | None = None
    disk_free_bytes: int | None = None
    recorder_state: str = "idle"


HEALTH_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(DeviceHealth))


@dataclass(frozen=True)
class _StreamCounters:
    poses_sent: int = 0
    poses_dropped: int = 0
    keyframes_spooled: int = 0
    keyframes_pending: int = 0


@dataclass(frozen=True)
class Status(_StreamCounters, DeviceHealth, _StatusHeader):
    """Device health and streaming counters: ``session_id, t_ns``, the :class:`DeviceHealth` fields,
    then the streamer's counters (``poses_sent, poses_dropped, keyframes_spooled, keyframes_pending``)."""

    @property
    def health(self) -> DeviceHealth:
        return DeviceHealth(**{k: getattr(self, k) for k in HEALTH_FIELDS})


@dataclass(frozen=True)
class Hello:
    """Host -> device: start (or restart) the keyframe flow.

    ``session_id``/``acked_seq``: the last session the host stored keyframes of, and the highest
    seq it holds contiguously from 0 (-1: none); ``credit``: the host's window.
    """

    session_id: str | None
    acked_seq: int
    credit: int


@dataclass(frozen=True)
class Ack:
    """Host -> device: keyframe ``seq`` of ``session_id`` is stored; grants ``credit`` more."""

    session_id: str
    seq: int
    credit: int = 1


@dataclass(frozen=True)
class Credit:
    """Host -> device: ``n`` more keyframes may be sent."""

    n: int


@dataclass(frozen=True)
class WorldRebase:
    """Device -> host: the on-board estimator redefined its world once during the session (a start in
    motion, levelled when gravity became known).  The session's poses and keyframes timed before
    ``from_t_ns`` were given in the earlier world; ``T_new_old`` (a rigid motion, sent as position and
    unit quaternion) maps them into the one the later poses are in."""

    session_id: str
    from_t_ns: int
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]

    @property
    def T_new_old(self) -> np.ndarray:
        return pose_matrix(self.position_m, self.quat_xyzw)


Message = Pose | Keyframe | Status | SessionInfo | Hello | Ack | Credit | WorldRebase


# --------------------------------------------------------------------------- helpers


def new_session_id() -> str:
    """``YYYYmmddTHHMMSSZ-xxxxxx`` (UTC time plus 6 random hex digits), a valid session id."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


def check_session_id(sid: object) -> str:
    """Return ``sid`` if it is a valid session id, else raise :class:`ProtocolError`."""
    if not isinstance(sid, str) or not SESSION_ID_RE.match(sid):
        raise DecodeError("field", f"session id {sid!r} must match {SESSION_ID_RE.pattern}")
    return sid


def rig_reference(rig: Rig) -> tuple[str, str]:
    """``(name, hash)`` of a :class:`stereopath.device.core.rig.Rig`: a 16-hex-digit SHA-256 of its calibration."""
    from stereopath.device.core.rig import rig_to_dict

    data = rig_to_dict(rig)
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    name = re.sub(r"[^A-Za-z0-9_.+-]", "_", str(rig.name))[:64] or "rig"
    return name, hashlib.sha256(text.encode()).hexdigest()[:16]


def pose_from_matrix(session_id: str, seq: int, t_ns: int, T_world_cam: np.ndarray, tracking: str = "ok",
                     inliers: int = 0, keyframe: bool = False) -> Pose:
    """Build a :class:`Pose` from a 4x4 ``T_world_cam``."""
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    T = np.asarray(T_world_cam, dtype=float)
    if T.shape != (4, 4):
        raise ProtocolError(f"pose: T_world_cam must be 4x4, got shape {T.shape}")
    q = matrix_to_quat_xyzw(T[:3, :3])
    return Pose(session_id, int(seq), int(t_ns), tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                tuple(float(v) for v in q), tracking, int(inliers), bool(keyframe))  # type: ignore[arg-type]


def pose_matrix(p: tuple[float, ...], q: tuple[float, ...]) -> np.ndarray:
    from stereopath.device.core.geometry import make_pose, quat_xyzw_to_matrix

    return make_pose(quat_xyzw_to_matrix(np.asarray(q, dtype=float)), np.asarray(p, dtype=float))
