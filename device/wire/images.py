"""Keyframe images on the wire: JPEG, PNG or allow-listed raw pixels, their headers checked before decoding."""

from __future__ import annotations

from typing import Any

import numpy as np

from stereopath.device.errors import ProtocolError
from stereopath.device.wire.fields import exact_keys
from stereopath.device.wire.messages import IMAGE_CHANNELS, IMAGE_ENCODINGS, MAX_IMAGE_SIDE, RAW_DTYPES, DecodeError, \
    EncodedImage


def encode_image(img: np.ndarray, encoding: str = "jpg", jpeg_quality: int = 90, png_compression: int = 1) -> EncodedImage:
    """Encode an 8-bit (or, for PNG/raw, 16-bit) grey or BGR image for a keyframe."""
    if encoding not in IMAGE_ENCODINGS:
        raise ProtocolError(f"image encoding {encoding!r} must be one of {IMAGE_ENCODINGS}")
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    shape = tuple(int(s) for s in a.shape)
    check_shape(shape, "image")
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


def check_shape(shape: tuple[int, ...], what: str) -> None:
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


def pack_image(img: EncodedImage) -> dict[str, Any]:
    return {"enc": img.encoding, "shape": list(img.shape), "dtype": img.dtype, "data": img.data}


def decode_image_field(obj: object, key: str) -> EncodedImage:
    if not isinstance(obj, dict):
        raise DecodeError("field", f"{key} must be a map")
    exact_keys(obj, _IMAGE_KEYS, key)
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
        check_shape(shp, key)
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
