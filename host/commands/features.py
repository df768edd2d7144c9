"""Count keypoints, matches and correct matches between two images for a feature preset.

A match is correct when the second image's keypoint lies within --tolerance
pixels (default 3) of the first keypoint mapped by the ground-truth homography
(--homography, Oxford/OpenCV XML as in the affine-covariant data sets, or a
plain-text 3x3 matrix).  Presets with the paper's asymmetric pairing (`paper`,
`fast_asym`) give IMG1 plain SIFT (the original view) and IMG2 the affine views;
symmetric presets (`full`, `fast`) give both images views (`fast` only those of the view pairs
its low-resolution pass keeps, Morel & Yu's two-resolution scheme); `sift` is SIFT on both.
Times: detect_s = detection on both images (that pass included), match_s = matching; the
*_cpu_s fields are the same as process CPU time of all threads.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stereopath.device.commands.arg_types import finite_number


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("img1", nargs="?", help="first (earlier) image")
    p.add_argument("img2", nargs="?", help="second (later) image")
    p.add_argument("--preset", default="fast", help="feature preset (see --list-presets; default fast)")
    p.add_argument("--homography", metavar="H1toNp.xml", help="ground-truth homography IMG1 -> IMG2")
    p.add_argument("--tolerance", type=finite_number("pixels", allow_minimum=False), default=3.0, help="pixel tolerance of a correct match (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--list-presets", action="store_true", help="list the feature presets and exit")


def _read_gray(path: str):
    import cv2

    from stereopath.device.errors import DatasetError

    if not Path(path).is_file():
        raise DatasetError(f"image not found: {path}")
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DatasetError(f"cannot decode image: {path}")
    return img


def run(args: argparse.Namespace) -> int:
    from stereopath.device.core.features import PRESET_HELP, PRESETS, get_preset
    from stereopath.device.errors import ConfigError
    from stereopath.host.evaluation.features import compare_pair, load_homography

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
