"""Decoding of dataset images into 8-bit grey arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereopath.device.errors import DatasetError


def read_gray(path: Path) -> np.ndarray:
    """Image file -> 2-D uint8 array.  Colour is converted to grey; 16-bit is scaled down.

    A missing file or one that does not decode raises :class:`DatasetError`.
    """
    import cv2

    if not path.is_file():
        raise DatasetError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise DatasetError(f"image cannot be decoded: {path}")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise DatasetError(f"{path}: unsupported number of channels {img.shape[2]}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DatasetError(f"{path}: unsupported pixel type {img.dtype}")
    return np.ascontiguousarray(img)
