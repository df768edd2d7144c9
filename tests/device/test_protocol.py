"""Wire protocol: round trips, the pose size bound, validation of untrusted bytes, fuzzing."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from stereopath.device.errors import ProtocolError
from stereopath.device.core.geometry import euler_xyz_to_matrix, make_pose
from stereopath.device.wire.protocol import (
    CONTROL_LIMITS, KEYFRAME_LIMITS, POSE_LIMITS, POSE_MAX_BYTES, PROTOCOL_VERSION, Ack, Credit, DecodeError,
    EncodedImage, Hello, Keyframe, Pose, Status, decode_control, decode_image, decode_keyframe, decode_message,
    decode_pose, decode_status, encode_ack, encode_credit, encode_hello, encode_image, encode_keyframe,
    encode_message, encode_pose, encode_status, make_keyframe, new_session_id, pose_from_matrix, rig_reference)
from stereopath.device.core.rig import paper_rig

RIG = ("paper", "0123456789abcdef")


def _pose(**kw) -> Pose:
    base = dict(session_id="20250101T000000Z-abcdef", seq=12, t_ns=1_234_567_890_123,
                position_m=(1.25, -0.5, 3.0), quat_xyzw=(0.0, 0.0, 0.0, 1.0), tracking="ok", inliers=140,
                keyframe=True)
    base.update(kw)
    return Pose(**base)


def _images(color: bool = False, dtype=np.uint8) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    shape = (6, 8, 3) if color else (6, 8)
    hi = 255 if dtype == np.uint8 else 65535
    blocks = rng.integers(0, hi, shape).astype(dtype)  # 8x8 blocks: texture JPEG keeps well
    left = np.repeat(np.repeat(blocks, 8, axis=0), 8, axis=1)
    return left, left[::-1].copy()


def _keyframe(encoding: str = "jpg", **kw) -> Keyframe:
    left, right = _images(**kw)
    T = make_pose(euler_xyz_to_matrix(np.radians([10, -5, 30])), [0.1, 0.2, 0.3])
    return make_keyframe("sessA", 3, 57, 99_000, T, (left, right), RIG, encoding)


def _raw(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _wire(msg_bytes: bytes) -> dict:
    return msgpack.unpackb(msg_bytes, raw=False)


# ----------------------------------------------------------------------------- round trips


def test_pose_round_trip_float32_precision():
    p = _pose()
    q = decode_pose(encode_pose(p))
    assert (q.session_id, q.seq, q.t_ns, q.tracking, q.inliers, q.keyframe) == \
        (p.session_id, p.seq, p.t_ns, "ok", 140, True)
    assert np.allclose(q.position_m, p.position_m, atol=1e-6)
    assert np.allclose(q.quat_xyzw, p.quat_xyzw, atol=1e-7)


def test_pose_from_matrix_round_trip():
    T = make_pose(euler_xyz_to_matrix(np.radians([20, 40, -70])), [1.5, -2.0, 0.25])
    q = decode_pose(encode_pose(pose_from_matrix("s", 1, 2, T, "imu_only", 7)))
    assert q.tracking == "imu_only"
    assert np.allclose(q.T_world_cam, T, atol=1e-5)


def test_pose_size_bound_worst_case():
    worst = _pose(session_id="x" * 31, seq=2**32 - 1, t_ns=2**63 - 1, position_m=(-999999.9,) * 3,
                  quat_xyzw=(0.5, -0.5, 0.5, -0.5), tracking="imu_only", inliers=10**6, keyframe=True)
    data = encode_pose(worst)
    assert len(data) <= POSE_MAX_BYTES
    assert decode_pose(data).inliers == 65535  # clipped to the wire range
    assert len(encode_pose(_pose(session_id=new_session_id()))) <= 112


def test_pose_is_one_map_with_version_and_type():
    obj = _wire(encode_pose(_pose()))
    assert obj["v"] == PROTOCOL_VERSION and obj["type"] == "pose"


@pytest.mark.parametrize("encoding", ["jpg", "png", "raw"])
@pytest.mark.parametrize("color", [False, True])
def test_keyframe_round_trip(encoding, color):
    kf = _keyframe(encoding, color=color)
    back = decode_keyframe(encode_keyframe(kf))
    assert back == kf
    assert np.allclose(back.T_world_cam, kf.T_world_cam)
    left = decode_image(back.left)
    expect = _images(color=color)[0]
    assert left.shape == expect.shape and left.dtype == np.uint8
    if encoding == "jpg":
        assert np.mean(np.abs(left.astype(float) - expect)) < 12  # lossy but the same image
    else:
        assert np.array_equal(left, expect)


@pytest.mark.parametrize("encoding", ["png", "raw"])
def test_keyframe_16bit_images(encoding):
    kf = _keyframe(encoding, dtype=np.uint16)
    back = decode_keyframe(encode_keyframe(kf))
    img = decode_image(back.right)
    assert img.dtype == np.uint16 and np.array_equal(img, _images(dtype=np.uint16)[1])


def test_status_and_control_round_trips():
    st = Status("sessA", 5, 19.5, 199.0, 2, 1, None, 48.5, 123456789, "recording", 400, 3, 17, 1)
    assert decode_status(encode_status(st)) == st
    for msg in (Hello(None, -1, 8), Hello("sessA", 41, 16), Ack("sessA", 3, 1), Credit(5)):
        assert decode_control(encode_message(msg)) == msg


def test_rig_reference_is_stable_and_distinguishes_rigs():
    a = rig_reference(paper_rig())
    assert a == rig_reference(paper_rig())
    T = np.eye(4)
    T[0, 3] = 0.01
    b = rig_reference(paper_rig(T_body_cam0=T))
    assert a[0] == b[0] and a[1] != b[1] and len(a[1]) == 16


# ----------------------------------------------------------------------------- encoder validation


@pytest.mark.parametrize("kw", [
    {"position_m": (math.nan, 0.0, 0.0)}, {"quat_xyzw": (0.0, 0.0, 0.0, 2.0)}, {"tracking": "great"},
    {"session_id": "../etc"}, {"seq": -1}, {"seq": 2**32},
])
def test_encode_pose_rejects_invalid(kw):
    with pytest.raises(ProtocolError):
        encode_pose(_pose(**kw))


def test_encode_image_rejects_bad_input():
    with pytest.raises(ProtocolError, match="uint8"):
        encode_image(np.zeros((4, 4), np.uint16), "jpg")
    with pytest.raises(ProtocolError, match="dtype"):
        encode_image(np.zeros((4, 4), np.float32), "raw")
    with pytest.raises(ProtocolError, match="shape"):
        encode_image(np.zeros((4, 4, 2), np.uint8), "raw")
    with pytest.raises(ProtocolError, match="encoding"):
        encode_image(np.zeros((4, 4), np.uint8), "bmp")


# ----------------------------------------------------------------------------- decoder validation


def _reason(data: bytes, limits=KEYFRAME_LIMITS, allowed=None) -> str:
    with pytest.raises(DecodeError) as info:
        decode_message(data, limits, allowed)
    return info.value.reason


def test_newer_version_rejected_with_clear_message():
    obj = _wire(encode_pose(_pose()))
    obj["v"] = PROTOCOL_VERSION + 1
    with pytest.raises(DecodeError, match=r"newer than this stereopath supports") as info:
        decode_pose(_raw(obj))
    assert info.value.reason == "version"
    obj["v"] = 0
    assert _reason(_raw(obj), POSE_LIMITS) == "field"
    obj["v"] = True
    assert _reason(_raw(obj), POSE_LIMITS) == "field"


def test_type_checks():
    assert _reason(_raw({"v": 1, "type": "nonsense"})) == "type"
    assert _reason(encode_pose(_pose()), CONTROL_LIMITS, ("hello", "ack", "credit")) == "type"
    assert _reason(_raw([1, 2, 3])) == "malformed"
    assert _reason(_raw("pose")) == "malformed"


@pytest.mark.parametrize("key,value", [
    ("seq", "12"), ("seq", True), ("seq", -3), ("seq", 2**40), ("t", 1.5), ("p", [1.0, 2.0]),
    ("p", [1.0, 2.0, float("nan")]), ("p", [1.0, 2.0, 1e9]), ("q", [0.0, 0.0, 0.0, 0.5]), ("q", "abcd"),
    ("st", 7), ("kf", 1), ("n", -1), ("sid", "../../x"), ("sid", "a/b"), ("sid", ""), ("sid", 5),
    ("sid", "x" * 32),
])
def test_pose_field_checks(key, value):
    obj = _wire(encode_pose(_pose()))
    obj[key] = value
    assert _reason(_raw(obj), POSE_LIMITS) == "field"


def test_exact_key_set():
    obj = _wire(encode_pose(_pose()))
    obj["extra"] = 1
    assert _reason(_raw(obj), POSE_LIMITS) == "field"
    del obj["extra"], obj["n"]
    assert _reason(_raw(obj), POSE_LIMITS) == "field"


def test_image_payload_checks():
    good = _wire(encode_keyframe(_keyframe("raw")))

    def variant(**img):
        obj = _wire(encode_keyframe(_keyframe("raw")))
        obj["l"].update(img)
        return _raw(obj)

    assert decode_keyframe(_raw(good)).left.shape == (48, 64)
    assert _reason(variant(dtype="<f8")) == "image"            # not in the allow-list
    assert _reason(variant(dtype="|O")) == "image"
    assert _reason(variant(data=b"\0" * 10)) == "image"         # size mismatch
    assert _reason(variant(shape=[48, 64, 2])) == "image"
    assert _reason(variant(shape=[10**6, 10**6])) == "image"
    assert _reason(variant(shape=[48.0, 64])) == "field"
    assert _reason(variant(enc="gif")) == "image"
    jpg = _wire(encode_keyframe(_keyframe("jpg")))
    jpg["l"]["shape"] = [10, 10]  # header says 64x48
    assert _reason(_raw(jpg)) == "image"
    png = _wire(encode_keyframe(_keyframe("png")))
    png["r"]["data"] = png["r"]["data"][:20]
    assert _reason(_raw(png)) == "image"
    png = _wire(encode_keyframe(_keyframe("png")))
    png["r"]["dtype"] = "<u2"  # header says 8-bit
    assert _reason(_raw(png)) == "image"


def test_declared_image_that_does_not_decode():
    kf = _keyframe("png")
    bad = EncodedImage("png", kf.left.data[:40], kf.left.shape, "|u1")  # valid header, truncated body
    with pytest.raises(DecodeError):
        decode_image(bad)


def test_msgpack_limits_and_size_bound():
    assert _reason(b"\xc6\xff\xff\xff\xff" + b"x" * 10) == "malformed"        # huge declared bin
    assert _reason(b"\xdd\xff\xff\xff\xff" + b"\x00" * 10) == "malformed"     # huge declared array
    assert _reason(b"\xdf\xff\xff\xff\xff" + b"\x00" * 10) == "malformed"     # huge declared map
    assert _reason(b"\xdb\xff\xff\xff\xff" + b"a" * 10) == "malformed"        # huge declared str
    assert _reason(b"\x91" * 5000 + b"\x00") == "malformed"                   # deep nesting
    assert _reason(_raw({"v": 1, "type": "pose", "x": msgpack.ExtType(5, b"abc")})) == "malformed"  # ext
    assert _reason(_raw({"v": 1, "type": "hello", "sid": "a" * 100, "acked": 1, "credit": 1}), CONTROL_LIMITS) \
        == "malformed"                                                       # str over max_str_len
    assert _reason(_raw({str(i): i for i in range(40)})) == "malformed"       # map over max_map_len
    assert _reason(encode_pose(_pose()) + b"\x00") == "malformed"             # trailing data
    assert _reason(b"") == "malformed"
    assert _reason(b"\x00" * 300, POSE_LIMITS) == "too_large"
    big = _raw({"v": 1, "type": "keyframe", "blob": b"\0" * (CONTROL_LIMITS.max_message_bytes + 1)})
    assert _reason(big, CONTROL_LIMITS) == "too_large"


def test_bin_over_max_bin_len_rejected():
    obj = _wire(encode_keyframe(_keyframe("raw")))
    obj["l"]["data"] = b"\0" * 100
    small = type(KEYFRAME_LIMITS)(max_message_bytes=10**6, max_bin_len=50)
    assert _reason(_raw(obj), small) == "malformed"


# ----------------------------------------------------------------------------- fuzzing


def _fuzz_inputs(rng: np.random.Generator, n: int) -> list[tuple[str, bytes]]:
    valid = [encode_pose(_pose()), encode_keyframe(_keyframe("png")), encode_keyframe(_keyframe("raw")),
             encode_status(Status("s", 1)), encode_hello(Hello("s", 3, 8)), encode_ack(Ack("s", 1)),
             encode_credit(Credit(2))]
    # values no field accepts (a None, -1 or 1.5 can be valid for some fields)
    wrong_values = ["../x", b"\0", [], {}, [[[]]], {"a": {"b": 1}}, 2**64 - 1, -(2**63), float("inf")]
    out: list[tuple[str, bytes]] = []
    for i in range(n):
        kind = i % 8
        base = valid[int(rng.integers(len(valid)))]
        if kind == 0:
            out.append(("random", rng.bytes(int(rng.integers(1, 400)))))
        elif kind == 1:
            out.append(("truncated", base[: int(rng.integers(1, len(base)))]))
        elif kind == 2:
            obj = _wire(base)
            key = list(obj)[int(rng.integers(len(obj)))]
            obj[key] = wrong_values[int(rng.integers(len(wrong_values)))]
            out.append(("wrong_type", _raw(obj)))
        elif kind == 3:
            head = bytes([0xC6, 0xDB, 0xDD, 0xDF, 0xC5, 0xDA, 0xDC, 0xDE][int(rng.integers(8))])
            out.append(("huge_length", head + b"\xff\xff\xff\xff"[: 4 if head[0] in (0xC6, 0xDB, 0xDD, 0xDF) else 2]
                        + rng.bytes(int(rng.integers(0, 50)))))
        elif kind == 4:
            depth = int(rng.integers(50, 3000))
            opener = b"\x91" if rng.random() < 0.5 else b"\x81\xa1k"
            out.append(("deep", opener * depth + b"\xc0"))
        elif kind == 5:
            b = bytearray(base)
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(len(b)))] = int(rng.integers(256))
            out.append(("mutated", bytes(b)))
        elif kind == 6:
            out.append(("oversized", base + rng.bytes(int(rng.integers(1, 64)))))  # trailing garbage
        else:
            obj = _wire(base)
            obj["v"] = int(rng.integers(PROTOCOL_VERSION + 1, 10**6))
            out.append(("version", _raw(obj)))
    return out


def test_fuzz_decoders_10000_inputs():
    rng = np.random.default_rng(20240601)
    inputs = _fuzz_inputs(rng, 10_000)
    channels = [(POSE_LIMITS, ("pose",)), (KEYFRAME_LIMITS, ("keyframe", "status")),
                (CONTROL_LIMITS, ("hello", "ack", "credit")), (KEYFRAME_LIMITS, None)]
    rejected: dict[str, int] = {}
    accepted_mutations = 0
    for i, (kind, data) in enumerate(inputs):
        limits, allowed = channels[i % len(channels)]
        try:
            msg = decode_message(data, limits, allowed)
        except DecodeError as exc:  # anything else (a crash) fails the test
            rejected[exc.reason] = rejected.get(exc.reason, 0) + 1
            continue
        # only a byte flip can leave a message valid (e.g. inside a float or an image byte)
        assert kind == "mutated", f"{kind} input accepted: {data[:60]!r}"
        assert isinstance(msg, (Pose, Keyframe, Status, Hello, Ack, Credit))
        accepted_mutations += 1
    assert sum(rejected.values()) + accepted_mutations == 10_000
    assert accepted_mutations < 1250  # most mutations are caught
    assert rejected.get("version", 0) >= 1000 * 0.5  # newer versions on channels that carry the type
    assert set(rejected) <= {"malformed", "too_large", "field", "type", "version", "image"}


# ----------------------------------------------------------------------------- arithmetic errors


def _session_obj() -> dict:
    from stereopath.device.wire.protocol import encode_session, make_session_info
    rig = paper_rig()
    return _wire(encode_session(make_session_info("20250101T000000Z-abcdef", rig, rig_reference(rig))))


def test_session_with_infinite_image_size_is_a_decode_error():
    from stereopath.device.wire.protocol import SESSION_LIMITS
    obj = _session_obj()
    obj["cal"]["cam0"]["image_size"] = [math.inf, 480]
    with pytest.raises(DecodeError, match="image_size") as info:
        decode_message(_raw(obj), SESSION_LIMITS)
    assert info.value.reason == "rig"


def test_arithmetic_errors_in_validators_become_decode_errors(monkeypatch):
    import stereopath.device.core.rig as rig_module
    import stereopath.device.wire.protocol as protocol
    from stereopath.device.wire.protocol import SESSION_LIMITS

    def overflow(*args, **kwargs):
        raise OverflowError("cannot convert float infinity to integer")

    monkeypatch.setattr(rig_module, "rig_from_dict", overflow)  # rig_of imports it at call time
    assert _reason(_raw(_session_obj()), SESSION_LIMITS) == "rig"
    monkeypatch.setitem(protocol._DECODERS, "hello", overflow)
    data = encode_hello(Hello("20250101T000000Z-abcdef", 1, 4))
    assert _reason(data, CONTROL_LIMITS) == "field"


# ----------------------------------------------------------------------------- world rebase


def test_world_rebase_round_trip_and_its_checks():
    from stereopath.device.wire.protocol import WorldRebase, decode_rebase, encode_rebase, make_rebase

    G = make_pose(euler_xyz_to_matrix(np.radians([12, -3, 40])), [0.2, -0.1, 0.05])
    msg = make_rebase("sessA", 1_500_000_000, G)
    data = encode_rebase(msg)
    assert len(data) < CONTROL_LIMITS.max_message_bytes
    back = decode_rebase(data)
    assert isinstance(back, WorldRebase) and back.session_id == "sessA" and back.from_t_ns == 1_500_000_000
    np.testing.assert_allclose(back.T_new_old, G, atol=1e-9)
    assert decode_message(encode_message(msg), KEYFRAME_LIMITS) == back
    with pytest.raises(ProtocolError, match="not a rigid motion"):
        make_rebase("sessA", 1, np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ProtocolError, match="finite 4x4"):
        make_rebase("sessA", 1, np.eye(3))
    good = _wire(data)
    for bad, what in (({**good, "q": [0.0, 0.0, 0.5, 0.5]}, "unit quaternion"), ({**good, "t": -1}, "t="),
                      ({**good, "p": [0.0, float("nan"), 0.0]}, "finite"), ({**good, "x": 1}, "rebase"),
                      ({k: v for k, v in good.items() if k != "p"}, "rebase")):
        with pytest.raises(DecodeError, match=what) as exc:
            decode_message(_raw(bad), KEYFRAME_LIMITS, ("rebase",))
        assert exc.value.reason == "field"
