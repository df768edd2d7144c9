"""The wire protocol between device and host: msgpack messages, encoders and decoders side by side.

Every message is one msgpack map with a schema version ``v`` and a ``type``:

``pose``      live pose, one ZeroMQ frame of at most :data:`POSE_MAX_BYTES` bytes (float32
              position and quaternion, short keys) -- PUB/SUB, lossy;
``keyframe``  pose plus the left and right images (JPEG or PNG, or raw pixels whose dtype and
              shape come from an allow-list) and the rig calibration reference (name + hash)
              -- ROUTER/DEALER, loss-free;
``session``   a session's rig calibration (the rig YAML schema, checked against its hash) and
              how many keyframes the device holds of it, once per session on each connection
              before its keyframes (also for an earlier session's undelivered keyframes);
``status``    device health, about 1 Hz (frame and IMU rates, drops, CPU, temperature, disk,
              recorder state) plus streaming counters -- on the keyframe channel;
``rebase``    the session's world was redefined once (a start in motion): the rigid motion
              ``T_new_old`` (position and unit quaternion) of the poses timed before ``t`` --
              on the keyframe channel, with every status from then on (a host applies it once);
``hello``     host -> device: (re)start of the keyframe flow, with the host's last stored
              keyframe seq of the session it knows and its credit window;
``ack``       host -> device: keyframe ``seq`` of ``sid`` is stored, with more credit;
``credit``    host -> device: more credit.

Decoders take untrusted bytes.  They bound the input size, set every msgpack limit
(``max_bin_len``, ``max_str_len``, ``max_array_len``, ``max_map_len``, ``max_ext_len=0``), check
every field's type and range (exactly the documented keys, nothing more) and raise
:class:`DecodeError` (a :class:`ProtocolError`) carrying a short ``reason`` used for counting
rejected messages.  A message with a newer schema version than :data:`PROTOCOL_VERSION` is
rejected with a message saying so.  No pickle anywhere.

Session ids become directory names on the host, so they are restricted to
``[A-Za-z0-9][A-Za-z0-9_.-]{0,30}``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, TypeVar

import numpy as np

from stereopath.device.errors import ProtocolError
from stereopath.device.settings import StreamImageSettings
from stereopath.device.wire.fields import check_common, check_pose_fields, exact_keys, field_float, field_int, \
    field_quat, field_str, field_vec, pack, unpack
from stereopath.device.wire.images import check_shape, decode_image, decode_image_field, encode_image, \
    image_header_size, pack_image
from stereopath.device.wire.messages import (
    CONTROL_LIMITS, HEALTH_FIELDS, I63, IMAGE_CHANNELS, IMAGE_ENCODINGS, KEYFRAME_LIMITS, MAX_CREDIT, MAX_IMAGE_SIDE,
    MAX_POSITION_M, POSE_LIMITS, POSE_MAX_BYTES, PROTOCOL_VERSION, RAW_DTYPES, RECORDER_STATE_RE, RIG_HASH_RE,
    RIG_NAME_RE, SESSION_ID_RE, SESSION_LIMITS, TRACKING_STATES, U32, Ack, Credit, DecodeError, DeviceHealth,
    EncodedImage, Hello, Keyframe, Limits, Message, Pose, SessionInfo, Status, WorldRebase, check_session_id,
    new_session_id, pose_from_matrix, pose_matrix, rig_reference,
)

# the protocol's public names, one import away for both sides
__all__ = [
    "CONTROL_LIMITS", "HEALTH_FIELDS", "IMAGE_CHANNELS", "IMAGE_ENCODINGS", "KEYFRAME_LIMITS", "MAX_CREDIT",
    "MAX_IMAGE_SIDE", "POSE_LIMITS", "POSE_MAX_BYTES", "PROTOCOL_VERSION", "RAW_DTYPES", "RECORDER_STATE_RE",
    "RIG_HASH_RE", "RIG_NAME_RE", "SESSION_ID_RE", "SESSION_LIMITS", "TRACKING_STATES", "Ack", "Credit", "DecodeError",
    "DeviceHealth", "EncodedImage", "Hello", "Keyframe", "Limits", "Message", "Pose", "SessionInfo", "Status",
    "WorldRebase", "check_session_id", "decode_control", "decode_image", "decode_keyframe", "decode_message", "decode_pose",
    "decode_session", "decode_status", "encode_ack", "encode_credit", "encode_hello", "encode_image",
    "encode_keyframe", "encode_message", "encode_pose", "encode_session", "encode_status", "image_header_size",
    "make_keyframe", "make_session_info", "make_rebase", "encode_rebase", "decode_rebase", "new_session_id", "pose_from_matrix", "pose_matrix", "rig_of",
    "rig_reference",
]


def _header(obj: dict[str, Any]) -> str:
    v = obj.get("v")
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        raise DecodeError("field", f"schema version v={v!r} is not a positive integer")
    if v > PROTOCOL_VERSION:
        raise DecodeError("version", f"message schema version {v} is newer than this stereopath supports "
                                     f"(version {PROTOCOL_VERSION}); upgrade the receiving side")
    t = obj.get("type")
    if not isinstance(t, str) or t not in _DECODERS:
        raise DecodeError("type", f"unknown message type {t!r}")
    return t


# --------------------------------------------------------------------------- pose

if TYPE_CHECKING:
    from stereopath.device.core.rig import Rig

_M = TypeVar("_M")

_POSE_KEYS = ("type", "v", "sid", "seq", "t", "p", "q", "st", "n", "kf")


def encode_pose(msg: Pose) -> bytes:
    """One compact frame (<= 128 bytes): float32 position and quaternion, tracking as 0/1/2."""
    check_common(msg.session_id, msg.seq, msg.t_ns, "pose")
    p, q = check_pose_fields(msg.position_m, msg.quat_xyzw, "pose")
    if msg.tracking not in TRACKING_STATES:
        raise ProtocolError(f"pose: tracking {msg.tracking!r} must be one of {TRACKING_STATES}")
    inliers = min(max(int(msg.inliers), 0), 65535)
    data = pack({"type": "pose", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "t": int(msg.t_ns), "p": p, "q": q, "st": TRACKING_STATES.index(msg.tracking),
                  "n": inliers, "kf": bool(msg.keyframe)}, single_float=True)
    if len(data) > POSE_MAX_BYTES:  # cannot happen with the bounds above; kept as a guard
        raise ProtocolError(f"pose message is {len(data)} bytes, over {POSE_MAX_BYTES}")
    return data


def _decode_pose(obj: dict[str, Any]) -> Pose:
    exact_keys(obj, _POSE_KEYS, "pose")
    kf = obj["kf"]
    if not isinstance(kf, bool):
        raise DecodeError("field", f"kf={kf!r} must be a boolean")
    st = field_int(obj, "st", 0, len(TRACKING_STATES) - 1)
    return Pose(check_session_id(obj["sid"]), field_int(obj, "seq", 0, U32), field_int(obj, "t", 0, I63),
                field_vec(obj, "p", 3, MAX_POSITION_M), field_quat(obj, "q"),  # type: ignore[arg-type]
                TRACKING_STATES[st], field_int(obj, "n", 0, 65535), kf)


def decode_pose(data: bytes, limits: Limits = POSE_LIMITS) -> Pose:
    return _expect(decode_message(data, limits, ("pose",)), Pose)


# --------------------------------------------------------------------------- keyframe

_KEYFRAME_KEYS = ("type", "v", "sid", "seq", "fseq", "t", "p", "q", "rig", "l", "r")


def make_keyframe(session_id: str, seq: int, frame_seq: int, t_ns: int, T_world_cam: np.ndarray,
                  images: tuple[np.ndarray, np.ndarray], rig_ref: tuple[str, str],
                  encoding: str | StreamImageSettings = "jpg") -> Keyframe:
    """Encode both images ``(left, right)`` (``cv2.imencode`` for jpg/png) and build a :class:`Keyframe`;
    ``encoding`` is a ``[stream.images]`` section or just its encoding name (default quality)."""
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    T = np.asarray(T_world_cam, dtype=float)
    if T.shape != (4, 4):
        raise ProtocolError(f"keyframe: T_world_cam must be 4x4, got {T.shape}")
    coding = encoding if isinstance(encoding, StreamImageSettings) else StreamImageSettings(encoding=encoding)  # type: ignore[arg-type]
    li, ri = (encode_image(img, coding.encoding, coding.jpeg_quality, coding.png_compression) for img in images)
    q = matrix_to_quat_xyzw(T[:3, :3])
    return Keyframe(session_id, int(seq), int(frame_seq), int(t_ns), tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                    tuple(float(v) for v in q), li, ri, rig_ref[0], rig_ref[1])  # type: ignore[arg-type]


def encode_keyframe(msg: Keyframe) -> bytes:
    check_common(msg.session_id, msg.seq, msg.t_ns, "keyframe")
    if not 0 <= int(msg.frame_seq) <= U32:
        raise ProtocolError(f"keyframe: frame_seq {msg.frame_seq} out of range")
    p, q = check_pose_fields(msg.position_m, msg.quat_xyzw, "keyframe")
    if not RIG_NAME_RE.match(msg.rig_name) or not RIG_HASH_RE.match(msg.rig_hash):
        raise ProtocolError(f"keyframe: rig reference ({msg.rig_name!r}, {msg.rig_hash!r}) is malformed")
    for img in (msg.left, msg.right):
        if img.encoding not in IMAGE_ENCODINGS or img.dtype not in RAW_DTYPES:
            raise ProtocolError(f"keyframe: image {img.encoding}/{img.dtype} not allowed")
        check_shape(tuple(img.shape), "keyframe image")
    return pack({"type": "keyframe", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "fseq": int(msg.frame_seq), "t": int(msg.t_ns), "p": p, "q": q,
                  "rig": {"name": msg.rig_name, "hash": msg.rig_hash},
                  "l": pack_image(msg.left), "r": pack_image(msg.right)})


def _rig_ref_field(obj: dict[str, Any]) -> tuple[str, str]:
    """The ``rig`` field of a keyframe or session message: ``{"name": ..., "hash": ...}``."""
    rig = obj["rig"]
    if not isinstance(rig, dict):
        raise DecodeError("field", "rig must be a map")
    exact_keys(rig, ("name", "hash"), "rig")
    return field_str(rig, "name", RIG_NAME_RE), field_str(rig, "hash", RIG_HASH_RE)


def _decode_keyframe(obj: dict[str, Any]) -> Keyframe:
    exact_keys(obj, _KEYFRAME_KEYS, "keyframe")
    rig_name, rig_hash = _rig_ref_field(obj)
    return Keyframe(check_session_id(obj["sid"]), field_int(obj, "seq", 0, U32), field_int(obj, "fseq", 0, U32),
                    field_int(obj, "t", 0, I63), field_vec(obj, "p", 3, MAX_POSITION_M), field_quat(obj, "q"),  # type: ignore[arg-type]
                    decode_image_field(obj["l"], "l"), decode_image_field(obj["r"], "r"), rig_name, rig_hash)


def decode_keyframe(data: bytes, limits: Limits = KEYFRAME_LIMITS) -> Keyframe:
    return _expect(decode_message(data, limits, ("keyframe",)), Keyframe)


# --------------------------------------------------------------------------- status

_STATUS_FIELDS = (  # wire key, attribute, kind, lo, hi
    ("fps", "frame_rate_hz", "f", 0.0, 1e4),
    ("imu_hz", "imu_rate_hz", "f", 0.0, 1e5),
    ("drop", "dropped_frames", "i", 0, I63),
    ("imu_gaps", "imu_gaps", "i", 0, I63),
    ("cpu", "cpu_load_pct", "f?", 0.0, 1e5),
    ("temp", "temperature_c", "f?", -273.0, 500.0),
    ("disk", "disk_free_bytes", "i?", 0, I63),
    ("psent", "poses_sent", "i", 0, I63),
    ("pdrop", "poses_dropped", "i", 0, I63),
    ("kfs", "keyframes_spooled", "i", 0, I63),
    ("kfp", "keyframes_pending", "i", 0, I63),
)
_STATUS_KEYS = ("type", "v", "sid", "t", "rec") + tuple(f[0] for f in _STATUS_FIELDS)


def encode_status(msg: Status) -> bytes:
    check_common(msg.session_id, 0, msg.t_ns, "status")
    if not RECORDER_STATE_RE.match(msg.recorder_state):
        raise ProtocolError(f"status: recorder state {msg.recorder_state!r} must match {RECORDER_STATE_RE.pattern}")
    out: dict[str, Any] = {"type": "status", "v": PROTOCOL_VERSION, "sid": msg.session_id, "t": int(msg.t_ns),
                           "rec": msg.recorder_state}
    for key, attr, kind, lo, hi in _STATUS_FIELDS:
        value = getattr(msg, attr)
        if value is None and kind.endswith("?"):
            out[key] = None
            continue
        value = int(value) if kind.startswith("i") else float(value)
        if not (math.isfinite(value) and lo <= value <= hi):
            raise ProtocolError(f"status: {attr}={value!r} out of range [{lo}, {hi}]")
        out[key] = value
    return pack(out)


def _decode_status(obj: dict[str, Any]) -> Status:
    exact_keys(obj, _STATUS_KEYS, "status")
    values: dict[str, Any] = {}
    for key, attr, kind, lo, hi in _STATUS_FIELDS:
        if kind.endswith("?") and obj[key] is None:
            values[attr] = None
        elif kind.startswith("i"):
            values[attr] = field_int(obj, key, int(lo), int(hi))
        else:
            values[attr] = field_float(obj, key, lo, hi)
    return Status(check_session_id(obj["sid"]), field_int(obj, "t", 0, I63),
                  recorder_state=field_str(obj, "rec", RECORDER_STATE_RE), **values)


# --------------------------------------------------------------------------- world rebase

_REBASE_KEYS = ("type", "v", "sid", "t", "p", "q")


def make_rebase(session_id: str, from_t_ns: int, T_new_old: np.ndarray) -> WorldRebase:
    """The :class:`WorldRebase` of a 4x4 rigid motion (refused: not 4x4, not finite, not rigid)."""
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    T = np.asarray(T_new_old, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ProtocolError(f"rebase: T_new_old must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise ProtocolError("rebase: T_new_old is not a rigid motion")
    return WorldRebase(session_id, int(from_t_ns), tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                       tuple(float(v) for v in matrix_to_quat_xyzw(R)))  # type: ignore[arg-type]


def encode_rebase(msg: WorldRebase) -> bytes:
    check_common(msg.session_id, 0, msg.from_t_ns, "rebase")
    p, q = check_pose_fields(msg.position_m, msg.quat_xyzw, "rebase")
    return pack({"type": "rebase", "v": PROTOCOL_VERSION, "sid": msg.session_id, "t": int(msg.from_t_ns),
                 "p": p, "q": q})


def _decode_rebase(obj: dict[str, Any]) -> WorldRebase:
    exact_keys(obj, _REBASE_KEYS, "rebase")
    return WorldRebase(check_session_id(obj["sid"]), field_int(obj, "t", 0, I63),
                       field_vec(obj, "p", 3, MAX_POSITION_M), field_quat(obj, "q"))  # type: ignore[arg-type]


def decode_rebase(data: bytes, limits: Limits = CONTROL_LIMITS) -> WorldRebase:
    return _expect(decode_message(data, limits, ("rebase",)), WorldRebase)


# --------------------------------------------------------------------------- session

_SESSION_KEYS = ("type", "v", "sid", "rig", "cal", "kfs", "live")


def make_session_info(session_id: str, rig: Rig | None, rig_ref: tuple[str, str], keyframes: int = 0,
                      live: bool = True) -> SessionInfo:
    """The session message of a device session: ``rig`` (a Rig, or None) named by ``rig_ref``."""
    from stereopath.device.core.rig import rig_to_dict

    return SessionInfo(session_id, rig_ref[0], rig_ref[1], None if rig is None else rig_to_dict(rig),
                       int(keyframes), bool(live))


def encode_session(msg: SessionInfo) -> bytes:
    check_common(msg.session_id, msg.keyframes, 0, "session")
    if not RIG_NAME_RE.match(msg.rig_name) or not RIG_HASH_RE.match(msg.rig_hash):
        raise ProtocolError(f"session: rig reference ({msg.rig_name!r}, {msg.rig_hash!r}) is malformed")
    data = pack({"type": "session", "v": PROTOCOL_VERSION, "sid": msg.session_id,
                 "rig": {"name": msg.rig_name, "hash": msg.rig_hash}, "cal": msg.rig, "kfs": int(msg.keyframes),
                 "live": bool(msg.live)})
    if len(data) > SESSION_LIMITS.max_message_bytes:
        raise ProtocolError(f"session message is {len(data)} bytes, over {SESSION_LIMITS.max_message_bytes}")
    return data


def rig_of(msg: SessionInfo) -> Rig | None:
    """The :class:`stereopath.device.core.rig.Rig` a session message carries (None if it carries none).

    Raises :class:`DecodeError` when the calibration is not a valid rig or does not hash to the
    reference the session's keyframes carry.
    """
    from stereopath.device.core.rig import rig_from_dict
    from stereopath.device.errors import CalibrationError

    if msg.rig is None:
        return None
    try:
        rig = rig_from_dict(msg.rig, source=f"session {msg.session_id} rig")
    except (CalibrationError, TypeError, ValueError, ArithmeticError) as exc:
        raise DecodeError("rig", f"session {msg.session_id}: invalid rig calibration: {exc}") from None
    ref = rig_reference(rig)
    if ref[1] != msg.rig_hash:
        raise DecodeError("rig", f"session {msg.session_id}: the calibration hashes to {ref[1]}, not the "
                                 f"declared {msg.rig_hash}")
    return rig


def _decode_session(obj: dict[str, Any]) -> SessionInfo:
    exact_keys(obj, _SESSION_KEYS, "session")
    rig_name, rig_hash = _rig_ref_field(obj)
    cal, live = obj["cal"], obj["live"]
    if cal is not None and not isinstance(cal, dict):
        raise DecodeError("field", "cal must be a map or nil")
    if not isinstance(live, bool):
        raise DecodeError("field", f"live={live!r} must be a boolean")
    msg = SessionInfo(check_session_id(obj["sid"]), rig_name, rig_hash, cal, field_int(obj, "kfs", 0, U32), live)
    rig_of(msg)  # the calibration must be a valid rig with the declared hash
    return msg


def decode_session(data: bytes, limits: Limits = SESSION_LIMITS) -> SessionInfo:
    return _expect(decode_message(data, limits, ("session",)), SessionInfo)


# --------------------------------------------------------------------------- control


def encode_hello(msg: Hello) -> bytes:
    if msg.session_id is not None:
        check_common(msg.session_id, 0, 0, "hello")
    if not -1 <= int(msg.acked_seq) <= U32 or not 0 <= int(msg.credit) <= MAX_CREDIT:
        raise ProtocolError(f"hello: acked_seq {msg.acked_seq} or credit {msg.credit} out of range")
    return pack({"type": "hello", "v": PROTOCOL_VERSION, "sid": msg.session_id,
                  "acked": int(msg.acked_seq), "credit": int(msg.credit)})


def _decode_hello(obj: dict[str, Any]) -> Hello:
    exact_keys(obj, ("type", "v", "sid", "acked", "credit"), "hello")
    sid = obj["sid"]
    return Hello(None if sid is None else check_session_id(sid), field_int(obj, "acked", -1, U32),
                 field_int(obj, "credit", 0, MAX_CREDIT))


def encode_ack(msg: Ack) -> bytes:
    check_common(msg.session_id, msg.seq, 0, "ack")
    if not 0 <= int(msg.credit) <= MAX_CREDIT:
        raise ProtocolError(f"ack: credit {msg.credit} out of range")
    return pack({"type": "ack", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "credit": int(msg.credit)})


def _decode_ack(obj: dict[str, Any]) -> Ack:
    exact_keys(obj, ("type", "v", "sid", "seq", "credit"), "ack")
    return Ack(check_session_id(obj["sid"]), field_int(obj, "seq", 0, U32), field_int(obj, "credit", 0, MAX_CREDIT))


def encode_credit(msg: Credit) -> bytes:
    if not 0 <= int(msg.n) <= MAX_CREDIT:
        raise ProtocolError(f"credit: n={msg.n} out of range")
    return pack({"type": "credit", "v": PROTOCOL_VERSION, "n": int(msg.n)})


def _decode_credit(obj: dict[str, Any]) -> Credit:
    exact_keys(obj, ("type", "v", "n"), "credit")
    return Credit(field_int(obj, "n", 0, MAX_CREDIT))


def decode_control(data: bytes, limits: Limits = CONTROL_LIMITS) -> Hello | Ack | Credit:
    """Decode a host -> device message of the keyframe channel."""
    return decode_message(data, limits, ("hello", "ack", "credit"))  # type: ignore[return-value]


def decode_status(data: bytes, limits: Limits = KEYFRAME_LIMITS) -> Status:
    return _expect(decode_message(data, limits, ("status",)), Status)


# --------------------------------------------------------------------------- dispatch

_DECODERS: dict[str, Callable[[dict[str, Any]], Any]] = {
    "pose": _decode_pose,
    "keyframe": _decode_keyframe,
    "status": _decode_status,
    "session": _decode_session,
    "hello": _decode_hello,
    "ack": _decode_ack,
    "credit": _decode_credit,
    "rebase": _decode_rebase,
}


def encode_message(msg: Message) -> bytes:
    """Encode any message type."""
    encoders: dict[type, Callable[[Any], bytes]] = {
        Pose: encode_pose, Keyframe: encode_keyframe, Status: encode_status, SessionInfo: encode_session,
        Hello: encode_hello, Ack: encode_ack, Credit: encode_credit, WorldRebase: encode_rebase}
    for cls, encode in encoders.items():
        if isinstance(msg, cls):
            return encode(msg)
    raise ProtocolError(f"cannot encode {type(msg).__name__}")


def decode_message(data: bytes, limits: Limits, allowed: tuple[str, ...] | None = None) -> Message:
    """Decode untrusted bytes into one of the message types; ``allowed`` restricts the types."""
    obj = unpack(data, limits)
    msg_type = _header(obj)
    if allowed is not None and msg_type not in allowed:
        raise DecodeError("type", f"message type {msg_type!r} not expected here (expected {', '.join(allowed)})")
    try:
        return _DECODERS[msg_type](obj)
    except DecodeError:
        raise
    except (KeyError, TypeError, ValueError, ArithmeticError) as exc:  # defensive: a validator missed a case
        raise DecodeError("field", f"{msg_type}: {type(exc).__name__}: {exc}") from None


def _expect(msg: object, cls: type[_M]) -> _M:
    if not isinstance(msg, cls):  # decode_message already restricts the type
        raise DecodeError("type", f"expected {cls.__name__}, got {type(msg).__name__}")
    return msg
