"""Bounded msgpack packing and the field checks every decoder applies to untrusted input."""

from __future__ import annotations

import math
import re
from typing import Any, Iterable, Mapping

import msgpack

from stereopath.device.errors import ProtocolError
from stereopath.device.wire.messages import I63, MAX_POSITION_M, SESSION_ID_RE, U32, DecodeError, Limits


def pack(obj: Mapping[str, Any], single_float: bool = False) -> bytes:
    return msgpack.packb(obj, use_bin_type=True, use_single_float=single_float)


def unpack(data: object, limits: Limits) -> dict[str, Any]:
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


def exact_keys(obj: dict[str, Any], expected: tuple[str, ...], what: str) -> None:
    if set(obj) != set(expected) or len(obj) != len(expected):
        missing = sorted(set(expected) - set(obj))
        extra = sorted(map(str, set(obj) - set(expected)))
        raise DecodeError("field", f"{what}: missing keys {missing}, unexpected keys {extra}")


def field_int(obj: Mapping[str, Any], key: str, lo: int, hi: int) -> int:
    v = obj[key]
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise DecodeError("field", f"{key}={v!r} must be an integer in [{lo}, {hi}]")
    return int(v)


def field_float(obj: Mapping[str, Any], key: str, lo: float, hi: float, nullable: bool = False) -> float | None:
    v = obj[key]
    if v is None and nullable:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise DecodeError("field", f"{key}={v!r} must be a finite number in [{lo}, {hi}]")
    return float(v)


def field_str(obj: Mapping[str, Any], key: str, pattern: re.Pattern[str]) -> str:
    v = obj[key]
    if not isinstance(v, str) or not pattern.match(v):
        raise DecodeError("field", f"{key}={v!r} must match {pattern.pattern}")
    return v


def field_vec(obj: Mapping[str, Any], key: str, n: int, bound: float) -> tuple[float, ...]:
    v = obj[key]
    if not isinstance(v, list) or len(v) != n:
        raise DecodeError("field", f"{key} must be a list of {n} numbers")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or abs(x) > bound:
            raise DecodeError("field", f"{key} element {x!r} must be a finite number with |x| <= {bound}")
        out.append(float(x))
    return tuple(out)


def field_quat(obj: Mapping[str, Any], key: str) -> tuple[float, float, float, float]:
    q = field_vec(obj, key, 4, 1.01)
    norm = math.sqrt(sum(x * x for x in q))
    if abs(norm - 1.0) > 1e-3:
        raise DecodeError("field", f"{key} is not a unit quaternion (norm {norm:.6f})")
    return q  # type: ignore[return-value]


def check_pose_fields(position_m: Iterable[float], quat_xyzw: Iterable[float], what: str) -> tuple[list[float], list[float]]:
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


def check_common(session_id: str, seq: int, t_ns: int, what: str) -> None:
    if not isinstance(session_id, str) or not SESSION_ID_RE.match(session_id):
        raise ProtocolError(f"{what}: session id {session_id!r} must match {SESSION_ID_RE.pattern}")
    if not 0 <= int(seq) <= U32:
        raise ProtocolError(f"{what}: seq {seq} out of range [0, {U32}]")
    if not 0 <= int(t_ns) <= I63:
        raise ProtocolError(f"{what}: t_ns {t_ns} out of range")
