"""The wire protocol between device and host: msgpack messages, encoders and decoders side by side.

Every message is one msgpack map with a schema version ``v`` and a ``type``:

``pose``      live pose, one ZeroMQ frame of at most :data:`POSE_MAX_BYTES` bytes (float32
              position and quaternion, short keys) -- PUB/SUB, lossy;
``keyframe``  pose plus the left and right images (JPEG or PNG, or raw pixels whose dtype and
              shape come from an allow-list) and the rig calibration reference (name + hash)
              -- ROUTER/DEALER, loss-free;
``status``    device health, about 1 Hz (frame and IMU rates, drops, CPU, temperature, disk,
              recorder state) plus streaming counters -- on the keyframe channel;
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

import dataclasses
import hashlib
import json
import math
import re
import secrets
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import msgpack
import numpy as np

from stereopath.device.errors import ProtocolError

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
        return _pose_matrix(self.position_m, self.quat_xyzw)


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
        return _pose_matrix(self.position_m, self.quat_xyzw)


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


Message = Pose | Keyframe | Status | Hello | Ack | Credit


# --------------------------------------------------------------------------- helpers


def new_session_id() -> str:
    """``YYYYmmddTHHMMSSZ-xxxxxx`` (UTC time plus 6 random hex digits), a valid session id."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


def check_session_id(sid: Any) -> str:
    """Return ``sid`` if it is a valid session id, else raise :class:`ProtocolError`."""
    if not isinstance(sid, str) or not SESSION_ID_RE.match(sid):
        raise DecodeError("field", f"session id {sid!r} must match {SESSION_ID_RE.pattern}")
    return sid


def rig_reference(rig: Any) -> tuple[str, str]:
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


def _pose_matrix(p: tuple[float, ...], q: tuple[float, ...]) -> np.ndarray:
    from stereopath.device.core.geometry import make_pose, quat_xyzw_to_matrix

    return make_pose(quat_xyzw_to_matrix(np.asarray(q, dtype=float)), np.asarray(p, dtype=float))


def _pack(obj: Mapping[str, Any], single_float: bool = False) -> bytes:
    return msgpack.packb(obj, use_bin_type=True, use_single_float=single_float)


def _unpack(data: Any, limits: Limits) -> dict[str, Any]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError("malformed", f"expected bytes, got {type(data).__name__}")
    n = len(data)
    if n > limits.max_message_bytes:
        raise DecodeError("too_large", f"message of {n} bytes exceeds {limits.max_message_bytes}")
    if n == 0:
        raise DecodeError("malformed", "empty message")
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True,
            max_bin_len=limits.max_bin_len, max_str_len=limits.max_str_len,
            max_array_len=limits.max_array_len, max_map_len=limits.max_map_len, max_ext_len=0,
        )
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        # ExtraData, FormatError, StackError (deep nesting) and limit violations are ValueErrors
        raise DecodeError("malformed", f"not a valid bounded msgpack message ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise DecodeError("malformed", f"top level must be a map, got {type(obj).__name__}")
    return obj


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


def _keys(obj: dict[str, Any], expected: tuple[str, ...], what: str) -> None:
    if set(obj) != set(expected) or len(obj) != len(expected):
        missing = sorted(set(expected) - set(obj))
        extra = sorted(map(str, set(obj) - set(expected)))
        raise DecodeError("field", f"{what}: missing keys {missing}, unexpected keys {extra}")


def _int(obj: Mapping[str, Any], key: str, lo: int, hi: int) -> int:
    v = obj[key]
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise DecodeError("field", f"{key}={v!r} must be an integer in [{lo}, {hi}]")
    return int(v)


def _float(obj: Mapping[str, Any], key: str, lo: float, hi: float, nullable: bool = False) -> float | None:
    v = obj[key]
    if v is None and nullable:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise DecodeError("field", f"{key}={v!r} must be a finite number in [{lo}, {hi}]")
    return float(v)


def _str(obj: Mapping[str, Any], key: str, pattern: re.Pattern[str]) -> str:
    v = obj[key]
    if not isinstance(v, str) or not pattern.match(v):
        raise DecodeError("field", f"{key}={v!r} must match {pattern.pattern}")
    return v


def _vec(obj: Mapping[str, Any], key: str, n: int, bound: float) -> tuple[float, ...]:
    v = obj[key]
    if not isinstance(v, list) or len(v) != n:
        raise DecodeError("field", f"{key} must be a list of {n} numbers")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or abs(x) > bound:
            raise DecodeError("field", f"{key} element {x!r} must be a finite number with |x| <= {bound}")
        out.append(float(x))
    return tuple(out)


def _quat(obj: Mapping[str, Any], key: str) -> tuple[float, float, float, float]:
    q = _vec(obj, key, 4, 1.01)
    norm = math.sqrt(sum(x * x for x in q))
    if abs(norm - 1.0) > 1e-3:
        raise DecodeError("field", f"{key} is not a unit quaternion (norm {norm:.6f})")
    return q  # type: ignore[return-value]


def _check_pose_fields(position_m: Any, quat_xyzw: Any, what: str) -> tuple[list[float], list[float]]:
    p = [float(x) for x in position_m]
    q = [float(x) for x in quat_xyzw]
    if len(p) != 3 or len(q) != 4:
        raise ProtocolError(f"{what}: position needs 3 and quaternion 4 values")
    if not all(math.isfinite(x) and abs(x) <= MAX_POSITION_M for x in p):
        raise ProtocolError(f"{what}: position {p} is not finite or beyond {MAX_POSITION_M} m")
    norm = math.sqrt(sum(x * x for x in q))
    if not math.isfinite(norm) or abs(norm - 1.0) > 1e-3:
        raise ProtocolError(f"{what}: quaternion {q} is not a unit quaternion")
    q = [x / norm for x in q]
    return p, q


def _check_common(session_id: str, seq: int, t_ns: int, what: str) -> None:
    if not isinstance(session_id, str) or not SESSION_ID_RE.match(session_id):
        raise ProtocolError(f"{what}: session id {session_id!r} must match {SESSION_ID_RE.pattern}")
    if not 0 <= int(seq) <= U32:
        raise ProtocolError(f"{what}: seq {seq} out of range [0, {U32}]")
    if not 0 <= int(t_ns) <= I63:
        raise ProtocolError(f"{what}: t_ns {t_ns} out of range")


# --------------------------------------------------------------------------- pose

_POSE_KEYS = ("type", "v", "sid", "seq", "t", "p", "q", "st", "n", "kf")


def encode_pose(msg: Pose) -> bytes:
    """One compact frame (<= 128 bytes): float32 position and quaternion, tracking as 0/1/2."""
    _check_common(msg.session_id, msg.seq, msg.t_ns, "pose")
    p, q = _check_pose_fields(msg.position_m, msg.quat_xyzw, "pose")
    if msg.tracking not in TRACKING_STATES:
        raise ProtocolError(f"pose: tracking {msg.tracking!r} must be one of {TRACKING_STATES}")
    inliers = min(max(int(msg.inliers), 0), 65535)
    data = _pack({"type": "pose", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "t": int(msg.t_ns), "p": p, "q": q, "st": TRACKING_STATES.index(msg.tracking),
                  "n": inliers, "kf": bool(msg.keyframe)}, single_float=True)
    if len(data) > POSE_MAX_BYTES:  # cannot happen with the bounds above; kept as a guard
        raise ProtocolError(f"pose message is {len(data)} bytes, over {POSE_MAX_BYTES}")
    return data


def _decode_pose(obj: dict[str, Any]) -> Pose:
    _keys(obj, _POSE_KEYS, "pose")
    kf = obj["kf"]
    if not isinstance(kf, bool):
        raise DecodeError("field", f"kf={kf!r} must be a boolean")
    st = _int(obj, "st", 0, len(TRACKING_STATES) - 1)
    return Pose(check_session_id(obj["sid"]), _int(obj, "seq", 0, U32), _int(obj, "t", 0, I63),
                _vec(obj, "p", 3, MAX_POSITION_M), _quat(obj, "q"),  # type: ignore[arg-type]
                TRACKING_STATES[st], _int(obj, "n", 0, 65535), kf)


def decode_pose(data: bytes, limits: Limits = POSE_LIMITS) -> Pose:
    return _expect(decode_message(data, limits, ("pose",)), Pose)


# --------------------------------------------------------------------------- images


def encode_image(img: np.ndarray, encoding: str = "jpg", jpeg_quality: int = 90, png_compression: int = 1) -> EncodedImage:
    """Encode an 8-bit (or, for PNG/raw, 16-bit) grey or BGR image for a keyframe."""
    if encoding not in IMAGE_ENCODINGS:
        raise ProtocolError(f"image encoding {encoding!r} must be one of {IMAGE_ENCODINGS}")
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    shape = tuple(int(s) for s in a.shape)
    _check_shape(shape, "image")
    dtype = a.dtype.newbyteorder("<").str if a.dtype.itemsize > 1 else a.dtype.str
    if dtype not in RAW_DTYPES:
        raise ProtocolError(f"image dtype {a.dtype} not allowed (allowed: uint8, uint16)")
    if encoding == "raw":
        return EncodedImage("raw", np.ascontiguousarray(a, dtype=np.dtype(dtype)).tobytes(), shape, dtype)
    if encoding == "jpg" and dtype != "|u1":
        raise ProtocolError("JPEG keyframe images must be uint8; use png or raw for 16-bit")
    import cv2

    if encoding == "jpg":
        ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)])
    if not ok:
        raise ProtocolError(f"cv2.imencode failed for a {shape} {dtype} image as {encoding}")
    return EncodedImage(encoding, buf.tobytes(), shape, dtype)


def decode_image(img: EncodedImage) -> np.ndarray:
    """Pixels of a decoded keyframe image (grey (h, w) or BGR (h, w, 3)); checks the declared shape."""
    if img.encoding == "raw":
        return np.frombuffer(img.data, dtype=np.dtype(img.dtype)).reshape(img.shape)
    import cv2

    out = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if out is None:
        raise DecodeError("image", f"{img.encoding} payload could not be decoded")
    if tuple(out.shape) != tuple(img.shape) or out.dtype != np.dtype(img.dtype):
        raise DecodeError("image", f"decoded image {out.shape} {out.dtype} does not match declared "
                                   f"{img.shape} {img.dtype}")
    return out


def _check_shape(shape: tuple[int, ...], what: str) -> None:
    if len(shape) not in (2, 3) or not all(1 <= s <= MAX_IMAGE_SIDE for s in shape[:2]) \
            or (len(shape) == 3 and shape[2] not in IMAGE_CHANNELS):
        raise ProtocolError(f"{what}: shape {shape} not allowed (h, w <= {MAX_IMAGE_SIDE}, 1 or 3 channels)")


def image_header_size(data: bytes, encoding: str) -> tuple[int, int, int, int]:
    """``(width, height, channels, bits)`` read from a PNG IHDR or JPEG SOF header (no decoding)."""
    if encoding == "png":
        if len(data) < 33 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
            raise DecodeError("image", "PNG payload without a valid signature and IHDR chunk")
        w = int.from_bytes(data[16:20], "big")
        h = int.from_bytes(data[20:24], "big")
        bits, colour = data[24], data[25]
        channels = {0: 1, 2: 3}.get(colour)
        if channels is None:
            raise DecodeError("image", f"PNG colour type {colour} not allowed (grey or RGB only)")
        return w, h, channels, bits
    if encoding == "jpg":
        if len(data) < 4 or data[:2] != b"\xff\xd8":
            raise DecodeError("image", "JPEG payload without an SOI marker")
        i, n = 2, len(data)
        for _ in range(4096):  # bounded marker walk
            while i < n and data[i] == 0xFF:
                i += 1
            if i >= n:
                break
            marker = data[i]
            i += 1
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                continue
            if marker in (0xD9, 0xDA):
                break
            if i + 2 > n:
                break
            seg = int.from_bytes(data[i:i + 2], "big")
            if seg < 2:
                break
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                if i + 8 > n:
                    break
                bits = data[i + 2]
                h = int.from_bytes(data[i + 3:i + 5], "big")
                w = int.from_bytes(data[i + 5:i + 7], "big")
                return w, h, data[i + 7], bits
            i += seg
        raise DecodeError("image", "JPEG payload without a frame header (SOF) before the scan")
    raise DecodeError("image", f"no header check for encoding {encoding!r}")


_IMAGE_KEYS = ("enc", "shape", "dtype", "data")


def _pack_image(img: EncodedImage) -> dict[str, Any]:
    return {"enc": img.encoding, "shape": list(img.shape), "dtype": img.dtype, "data": img.data}


def _decode_image_field(obj: Any, key: str) -> EncodedImage:
    if not isinstance(obj, dict):
        raise DecodeError("field", f"{key} must be a map")
    _keys(obj, _IMAGE_KEYS, key)
    enc, dtype, data, shape = obj["enc"], obj["dtype"], obj["data"], obj["shape"]
    if enc not in IMAGE_ENCODINGS:
        raise DecodeError("image", f"{key}: encoding {enc!r} not one of {IMAGE_ENCODINGS}")
    if dtype not in RAW_DTYPES:
        raise DecodeError("image", f"{key}: dtype {dtype!r} not in the allow-list {RAW_DTYPES}")
    if not isinstance(data, bytes):
        raise DecodeError("field", f"{key}: data must be binary")
    if not isinstance(shape, list) or not all(isinstance(s, int) and not isinstance(s, bool) for s in shape):
        raise DecodeError("field", f"{key}: shape must be a list of integers")
    shp = tuple(shape)
    try:
        _check_shape(shp, key)
    except ProtocolError as exc:
        raise DecodeError("image", str(exc)) from None
    channels = shp[2] if len(shp) == 3 else 1
    if enc == "raw":
        expected = shp[0] * shp[1] * channels * np.dtype(dtype).itemsize
        if len(data) != expected:
            raise DecodeError("image", f"{key}: raw payload of {len(data)} bytes, expected {expected} for {shp} {dtype}")
    else:
        if enc == "jpg" and dtype != "|u1":
            raise DecodeError("image", f"{key}: JPEG must be declared |u1")
        w, h, c, bits = image_header_size(data, enc)
        want_bits = 8 * np.dtype(dtype).itemsize
        if (h, w, c, bits) != (shp[0], shp[1], channels, want_bits):
            raise DecodeError("image", f"{key}: {enc} header says {w}x{h}x{c} {bits}-bit, declared {shp} {dtype}")
    return EncodedImage(enc, data, shp, dtype)


# --------------------------------------------------------------------------- keyframe

_KEYFRAME_KEYS = ("type", "v", "sid", "seq", "fseq", "t", "p", "q", "rig", "l", "r")


def make_keyframe(session_id: str, seq: int, frame_seq: int, t_ns: int, T_world_cam: np.ndarray,
                  left: np.ndarray, right: np.ndarray, rig_ref: tuple[str, str], encoding: str = "jpg",
                  jpeg_quality: int = 90, png_compression: int = 1) -> Keyframe:
    """Encode both images (``cv2.imencode`` for jpg/png) and build a :class:`Keyframe`."""
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    T = np.asarray(T_world_cam, dtype=float)
    if T.shape != (4, 4):
        raise ProtocolError(f"keyframe: T_world_cam must be 4x4, got {T.shape}")
    li = encode_image(left, encoding, jpeg_quality, png_compression)
    ri = encode_image(right, encoding, jpeg_quality, png_compression)
    q = matrix_to_quat_xyzw(T[:3, :3])
    return Keyframe(session_id, int(seq), int(frame_seq), int(t_ns), tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                    tuple(float(v) for v in q), li, ri, rig_ref[0], rig_ref[1])  # type: ignore[arg-type]


def encode_keyframe(msg: Keyframe) -> bytes:
    _check_common(msg.session_id, msg.seq, msg.t_ns, "keyframe")
    if not 0 <= int(msg.frame_seq) <= U32:
        raise ProtocolError(f"keyframe: frame_seq {msg.frame_seq} out of range")
    p, q = _check_pose_fields(msg.position_m, msg.quat_xyzw, "keyframe")
    if not RIG_NAME_RE.match(msg.rig_name) or not RIG_HASH_RE.match(msg.rig_hash):
        raise ProtocolError(f"keyframe: rig reference ({msg.rig_name!r}, {msg.rig_hash!r}) is malformed")
    for img in (msg.left, msg.right):
        if img.encoding not in IMAGE_ENCODINGS or img.dtype not in RAW_DTYPES:
            raise ProtocolError(f"keyframe: image {img.encoding}/{img.dtype} not allowed")
        _check_shape(tuple(img.shape), "keyframe image")
    return _pack({"type": "keyframe", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "fseq": int(msg.frame_seq), "t": int(msg.t_ns), "p": p, "q": q,
                  "rig": {"name": msg.rig_name, "hash": msg.rig_hash},
                  "l": _pack_image(msg.left), "r": _pack_image(msg.right)})


def _decode_keyframe(obj: dict[str, Any]) -> Keyframe:
    _keys(obj, _KEYFRAME_KEYS, "keyframe")
    rig = obj["rig"]
    if not isinstance(rig, dict):
        raise DecodeError("field", "rig must be a map")
    _keys(rig, ("name", "hash"), "rig")
    return Keyframe(check_session_id(obj["sid"]), _int(obj, "seq", 0, U32), _int(obj, "fseq", 0, U32),
                    _int(obj, "t", 0, I63), _vec(obj, "p", 3, MAX_POSITION_M), _quat(obj, "q"),  # type: ignore[arg-type]
                    _decode_image_field(obj["l"], "l"), _decode_image_field(obj["r"], "r"),
                    _str(rig, "name", RIG_NAME_RE), _str(rig, "hash", RIG_HASH_RE))


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
    _check_common(msg.session_id, 0, msg.t_ns, "status")
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
    return _pack(out)


def _decode_status(obj: dict[str, Any]) -> Status:
    _keys(obj, _STATUS_KEYS, "status")
    values: dict[str, Any] = {}
    for key, attr, kind, lo, hi in _STATUS_FIELDS:
        if kind.endswith("?") and obj[key] is None:
            values[attr] = None
        elif kind.startswith("i"):
            values[attr] = _int(obj, key, int(lo), int(hi))
        else:
            values[attr] = _float(obj, key, lo, hi)
    return Status(check_session_id(obj["sid"]), _int(obj, "t", 0, I63),
                  recorder_state=_str(obj, "rec", RECORDER_STATE_RE), **values)


# --------------------------------------------------------------------------- control


def encode_hello(msg: Hello) -> bytes:
    if msg.session_id is not None:
        _check_common(msg.session_id, 0, 0, "hello")
    if not -1 <= int(msg.acked_seq) <= U32 or not 0 <= int(msg.credit) <= MAX_CREDIT:
        raise ProtocolError(f"hello: acked_seq {msg.acked_seq} or credit {msg.credit} out of range")
    return _pack({"type": "hello", "v": PROTOCOL_VERSION, "sid": msg.session_id,
                  "acked": int(msg.acked_seq), "credit": int(msg.credit)})


def _decode_hello(obj: dict[str, Any]) -> Hello:
    _keys(obj, ("type", "v", "sid", "acked", "credit"), "hello")
    sid = obj["sid"]
    return Hello(None if sid is None else check_session_id(sid), _int(obj, "acked", -1, U32),
                 _int(obj, "credit", 0, MAX_CREDIT))


def encode_ack(msg: Ack) -> bytes:
    _check_common(msg.session_id, msg.seq, 0, "ack")
    if not 0 <= int(msg.credit) <= MAX_CREDIT:
        raise ProtocolError(f"ack: credit {msg.credit} out of range")
    return _pack({"type": "ack", "v": PROTOCOL_VERSION, "sid": msg.session_id, "seq": int(msg.seq),
                  "credit": int(msg.credit)})


def _decode_ack(obj: dict[str, Any]) -> Ack:
    _keys(obj, ("type", "v", "sid", "seq", "credit"), "ack")
    return Ack(check_session_id(obj["sid"]), _int(obj, "seq", 0, U32), _int(obj, "credit", 0, MAX_CREDIT))


def encode_credit(msg: Credit) -> bytes:
    if not 0 <= int(msg.n) <= MAX_CREDIT:
        raise ProtocolError(f"credit: n={msg.n} out of range")
    return _pack({"type": "credit", "v": PROTOCOL_VERSION, "n": int(msg.n)})


def _decode_credit(obj: dict[str, Any]) -> Credit:
    _keys(obj, ("type", "v", "n"), "credit")
    return Credit(_int(obj, "n", 0, MAX_CREDIT))


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
    "hello": _decode_hello,
    "ack": _decode_ack,
    "credit": _decode_credit,
}


def encode_message(msg: Message) -> bytes:
    """Encode any message type."""
    if isinstance(msg, Pose):
        return encode_pose(msg)
    if isinstance(msg, Keyframe):
        return encode_keyframe(msg)
    if isinstance(msg, Status):
        return encode_status(msg)
    if isinstance(msg, Hello):
        return encode_hello(msg)
    if isinstance(msg, Ack):
        return encode_ack(msg)
    if isinstance(msg, Credit):
        return encode_credit(msg)
    raise ProtocolError(f"cannot encode {type(msg).__name__}")


def decode_message(data: bytes, limits: Limits, allowed: tuple[str, ...] | None = None) -> Message:
    """Decode untrusted bytes into one of the message types; ``allowed`` restricts the types."""
    obj = _unpack(data, limits)
    msg_type = _header(obj)
    if allowed is not None and msg_type not in allowed:
        raise DecodeError("type", f"message type {msg_type!r} not expected here (expected {', '.join(allowed)})")
    try:
        return _DECODERS[msg_type](obj)
    except DecodeError:
        raise
    except (KeyError, TypeError, ValueError) as exc:  # defensive: a validator missed a case
        raise DecodeError("field", f"{msg_type}: {type(exc).__name__}: {exc}") from None


def _expect(msg: Any, cls: type) -> Any:
    if not isinstance(msg, cls):  # decode_message already restricts the type
        raise DecodeError("type", f"expected {cls.__name__}, got {type(msg).__name__}")
    return msg
