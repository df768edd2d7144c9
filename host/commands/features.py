"""Count keypoints, matches and correct matches between two images for a feature preset.

A match is correct when the second image's keypoint lies within --tolerance
pixels (default 3) of the first keypoint mapped by the ground-truth homography
(--homography, Oxford/OpenCV XML as in the affine-covariant data sets, or a
plain-text 3x3 matrix).  Presets with the paper's asymmetric pairing (`paper`,
`fast`) give IMG1 plain SIFT (the original view) and IMG2 the affine views;
symmetric presets (`full`, `fast_sym`) give both images all views; `sift` is
SIFT on both.  Times: detect_s = detection on both images, match_s = matching.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("img1", nargs="?", help="first (earlier) image")
    p.add_argument("img2", nargs="?", help="second (later) image")
    p.add_argument("--preset", default="fast", help="feature preset (see --list-presets; default fast)")
    p.add_argument("--homography", metavar="H1toNp.xml", help="ground-truth homography IMG1 -> IMG2")
    p.add_argument("--tolerance", type=float, default=3.0, help="pixel tolerance of a correct match (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--list-presets", action="store_true", help="list the feature presets and exit")


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
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        try:
            node = fs.getFirstTopLevelNode()
            H = None if node is None or node.empty() else node.mat()
        finally:
            fs.release()
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


def _read_gray(path: str):
    import cv2

    from stereopath.device.errors import DatasetError

    if not Path(path).is_file():
        raise DatasetError(f"image not found: {path}")
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DatasetError(f"cannot decode image: {path}")
    return img


def compare_pair(img1, img2, preset: str, homography=None, tolerance: float = 3.0, match_cfg=None) -> dict:
    """Detect, match and (with a homography) count correct matches; returns the JSON record."""
    from stereopath.device.core.features import detect, earlier_features, get_preset
    from stereopath.device.core.matching import MatchConfig, match

    cfg = get_preset(preset)
    t0 = time.perf_counter()
    f1 = earlier_features(img1, cfg)
    f2 = detect(img2, cfg)
    t1 = time.perf_counter()
    m = match(f1, f2, match_cfg or MatchConfig())
    t2 = time.perf_counter()
    correct = None
    if homography is not None:
        p1, p2 = m.points(f1, f2)
        correct = int(correct_mask(p1, p2, homography, tolerance).sum())
    return {
        "preset": preset,
        "keypoints1": len(f1),
        "keypoints2": len(f2),
        "matches": len(m),
        "correct": correct,
        "detect_s": round(t1 - t0, 4),
        "match_s": round(t2 - t1, 4),
    }


def run(args: argparse.Namespace) -> int:
    from stereopath.device.errors import ConfigError
    from stereopath.device.core.features import PRESET_HELP, PRESETS, get_preset

    if args.list_presets:
        for name, cfg in PRESETS.items():
            print(f"{name:9s} {cfg.n_views if cfg.backend == 'views' else 'cv2':>3} views  {cfg.pairing:10s}  {PRESET_HELP.get(name, '')}")
        return 0
    if not args.img1 or not args.img2:
        raise ConfigError("features needs two images (IMG1 IMG2), or --list-presets")
    if args.tolerance <= 0:
        raise ConfigError(f"--tolerance must be positive, got {args.tolerance}")
    get_preset(args.preset)  # unknown preset -> ConfigError before reading images
    img1 = _read_gray(args.img1)
    img2 = _read_gray(args.img2)
    H = load_homography(args.homography) if args.homography else None
    rec = compare_pair(img1, img2, args.preset, H, args.tolerance)
    if args.json:
        print(json.dumps(rec))
    else:
        out = sys.stdout
        out.write(f"preset      {rec['preset']}\n")
        out.write(f"keypoints   {rec['keypoints1']} / {rec['keypoints2']}\n")
        out.write(f"matches     {rec['matches']}\n")
        if rec["correct"] is not None:
            out.write(f"correct     {rec['correct']} (within {args.tolerance:g} px of the homography)\n")
        out.write(f"detect      {rec['detect_s']:.3f} s\n")
        out.write(f"match       {rec['match_s']:.3f} s\n")
    return 0
