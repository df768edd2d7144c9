"""Middlebury stereo scenes with ground-truth disparity: the pairs the depth benchmark scores.

Two layouts, told apart by their files:

* the 2001/2003 scenes as OpenCV's test data ships them (``tsukuba``, ``venus``, ``cones``,
  ``teddy``, ...): ``im2.png`` (left), ``im6.png`` (right), ``disp2.png`` (the left image's
  disparity times a per-scene scale factor, 0 = unknown); the factors come from ``datasets.xml``
  beside the scene folders (``name "scale" "unknown value"`` lines);
* the 2014/2021 scenes: ``im0.png``, ``im1.png``, ``disp0GT.pfm`` or ``disp0.pfm`` (float
  disparity, infinity = unknown) and ``calib.txt`` (``ndisp=``; the images are rectified, the
  disparity is in pixels of these images).

:func:`read_scene` gives the grey images, the ground truth (float32 px, NaN = unknown) and the
number of disparities to search; :func:`find_scenes` lists the scenes below a folder.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereopath.device.errors import DatasetError
from stereopath.device.formats.images import read_gray

DATASETS_XML = "datasets.xml"


@dataclass(frozen=True)
class Scene:
    name: str
    left: np.ndarray  # grey uint8
    right: np.ndarray
    gt: np.ndarray  # float32 disparity of the left image, NaN = unknown
    num_disparities: int  # a multiple of 16 covering the scene's disparities (what SGBM searches)


def read_scale_factors(path: Path) -> dict[str, tuple[float, float]]:
    """``datasets.xml``: scene name -> (disparity scale factor, value of unknown pixels)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {}
    out = {}
    for name, scale, unknown in re.findall(r'^\s*([\w-]+)\s+"([\d.]+)"\s+"([\d.]+)"\s*$', text, re.MULTILINE):
        if float(scale) <= 0:
            raise DatasetError(f"{path}: {name}: scale factor must be positive, got {scale}")
        out[name] = (float(scale), float(unknown))
    return out


def _num_disparities(max_disparity: float) -> int:
    return max(16, 16 * math.ceil((max_disparity + 1) / 16))


def _read_2003(d: Path) -> Scene:
    factors = read_scale_factors(d.parent / DATASETS_XML)
    if d.name not in factors:
        raise DatasetError(f"{d}: no disparity scale factor for {d.name!r} in {d.parent / DATASETS_XML}")
    scale, unknown = factors[d.name]
    left, right = read_gray(d / "im2.png"), read_gray(d / "im6.png")
    raw = read_gray(d / "disp2.png").astype(np.float32)
    gt = np.where(raw == unknown, np.nan, raw / scale).astype(np.float32)
    return _scene(d, left, right, gt, None)


def _read_2014(d: Path) -> Scene:
    import cv2

    pfm = next((d / n for n in ("disp0GT.pfm", "disp0.pfm") if (d / n).is_file()), None)
    if pfm is None:
        raise DatasetError(f"{d}: no disp0GT.pfm or disp0.pfm")
    gt = cv2.imread(str(pfm), cv2.IMREAD_UNCHANGED)
    if gt is None or gt.ndim != 2:
        raise DatasetError(f"{pfm}: not a one-channel PFM disparity map")
    gt = np.where(np.isfinite(gt) & (gt > 0), gt, np.nan).astype(np.float32)
    ndisp = None
    calib = d / "calib.txt"
    if calib.is_file():
        m = re.search(r"^\s*ndisp\s*=\s*(\d+)\s*$", calib.read_text(), re.MULTILINE)
        ndisp = int(m.group(1)) if m else None
    return _scene(d, read_gray(d / "im0.png"), read_gray(d / "im1.png"), gt, ndisp)


def _scene(d: Path, left: np.ndarray, right: np.ndarray, gt: np.ndarray, ndisp: int | None) -> Scene:
    if left.shape != right.shape or gt.shape != left.shape:
        raise DatasetError(f"{d}: left {left.shape}, right {right.shape} and ground truth {gt.shape} differ in size")
    known = gt[np.isfinite(gt)]
    if not known.size:
        raise DatasetError(f"{d}: the ground truth has no known pixel")
    top = max(float(known.max()), float(ndisp - 1) if ndisp else 0.0)
    return Scene(d.name, left, right, gt, _num_disparities(top))


def read_scene(scene_dir: str | Path) -> Scene:
    """One scene folder in either layout (see the module doc)."""
    d = Path(scene_dir)
    if (d / "im2.png").is_file() and (d / "disp2.png").is_file():
        return _read_2003(d)
    if (d / "im0.png").is_file():
        return _read_2014(d)
    raise DatasetError(f"{d}: not a Middlebury scene (im2.png/im6.png/disp2.png or im0.png/im1.png/disp0*.pfm)")


def find_scenes(root: str | Path) -> list[Path]:
    """The scene folders directly below ``root`` (either layout), sorted by name."""
    r = Path(root)
    if not r.is_dir():
        return []
    return sorted(p for p in r.iterdir() if p.is_dir() and ((p / "disp2.png").is_file() or (p / "im0.png").is_file()))
