"""Feature evaluation against a ground-truth homography (Oxford affine-covariant style data sets).

:func:`compare_pair` detects and matches two images with a feature preset and counts the
matches whose second point lies within a tolerance of the first mapped by the homography
(:func:`correct_mask`); :func:`load_homography` reads the homography file.
"""

from __future__ import annotations

import time
from pathlib import Path


def load_homography(path: str | Path):
    """3x3 homography from OpenCV XML/YAML (first matrix in the file) or a 3x3 text matrix."""
    import cv2
    import numpy as np

    from stereopath.device.errors import DatasetError

    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"homography file not found: {p}")
    head = p.read_text(errors="replace")[:64].lstrip()
    H = None
    if head.startswith("<?xml") or head.startswith("%YAML") or head.startswith("<opencv_storage"):
        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
            try:
                node = fs.getFirstTopLevelNode()
                H = None if node is None or node.empty() else node.mat()
            finally:
                fs.release()
        except (cv2.error, SystemError) as exc:  # a parse error comes out of cv2.FileStorage as SystemError
            detail = " ".join(str(exc.__cause__ or exc).split())[:200]
            raise DatasetError(f"{p}: not a readable OpenCV XML/YAML matrix file ({detail})") from None
    else:
        try:
            H = np.loadtxt(p, dtype=float)
        except ValueError as exc:
            raise DatasetError(f"{p}: not a 3x3 matrix: {exc}") from None
    if H is None or np.asarray(H).size != 9 or not np.isfinite(H).all():
        raise DatasetError(f"{p}: no finite 3x3 homography found")
    H = np.asarray(H, float).reshape(3, 3)
    if abs(H[2, 2]) > 1e-12:
        H = H / H[2, 2]
    return H


def correct_mask(p1, p2, H, tolerance: float = 3.0):
    """Boolean mask: ``p2`` within ``tolerance`` px of ``H`` applied to ``p1``."""
    import numpy as np

    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    if len(p1) == 0:
        return np.zeros(0, bool)
    h = np.hstack([p1, np.ones((len(p1), 1))]) @ np.asarray(H, float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = h[:, :2] / h[:, 2:3]
        err = np.linalg.norm(proj - p2, axis=1)
    return np.isfinite(err) & (err <= tolerance)


def compare_pair(img1, img2, preset: str, homography=None, tolerance: float = 3.0, match_cfg=None) -> dict:
    """Detect, match and (with a homography) count correct matches; returns the JSON record.

    ``detect_s`` / ``match_s`` are wall times, ``*_cpu_s`` the process CPU time of all threads;
    detection includes the preset's low-resolution view selection (``view_pairs``: how many view
    pairs it kept, ``None`` without selection).
    """
    from stereopath.device.core.features import get_preset
    from stereopath.device.core.matching import MatchConfig, match
    from stereopath.device.core.view_selection import detect_pair

    cfg = get_preset(preset)
    match_cfg = match_cfg or MatchConfig()
    t0, c0 = time.perf_counter(), time.process_time()
    f1, f2, pairs = detect_pair(img1, img2, cfg, match_cfg)  # the preset's view selection included
    t1, c1 = time.perf_counter(), time.process_time()
    m = match(f1, f2, match_cfg, only_pairs=pairs)
    t2, c2 = time.perf_counter(), time.process_time()
    correct = None
    if homography is not None:
        p1, p2 = m.points(f1, f2)
        correct = int(correct_mask(p1, p2, homography, tolerance).sum())
    return {
        "preset": preset,
        "keypoints1": len(f1),
        "keypoints2": len(f2),
        "matches": len(m),
        "view_pairs": None if pairs is None else len(pairs),
        "correct": correct,
        "detect_s": round(t1 - t0, 4),
        "match_s": round(t2 - t1, 4),
        "detect_cpu_s": round(c1 - c0, 4),  # process CPU time, all threads
        "match_cpu_s": round(c2 - c1, 4),
    }
