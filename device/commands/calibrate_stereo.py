"""Calibrate the stereo rig from chessboard image pairs and write our rig YAML.

IMAGES_DIR holds pairs named left<ID>.<ext> / right<ID>.<ext> (png, jpg, bmp, tif).
Prints per-pair detection, the RMS reprojection error and the baseline, and draws the error of
each pair (``--plot FILE``; by default ``<out>_reprojection.png`` beside ``--out``).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from stereopath.device.commands.arg_types import finite_number

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images_dir", metavar="IMAGES_DIR", help="folder with left*/right* chessboard images")
    parser.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    parser.add_argument("--square-mm", type=finite_number("millimetres", allow_minimum=False), required=True, help="chessboard square size in millimetres")
    parser.add_argument("--out", default=None, help="write the rig YAML here")
    parser.add_argument("--name", default="calibrated", help="rig name stored in the YAML")
    parser.add_argument("--plot", default=None, metavar="FILE.png",
                        help="write the reprojection error of each pair here (default with --out: "
                             "<out>_reprojection.png beside it; needs matplotlib, skipped without it)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the plot")
    parser.add_argument("--max-rms", type=finite_number("pixels", allow_minimum=False), default=1.0,
                        help="fail (exit 1) when the stereo RMS error exceeds this many pixels (default 1.0)")


def find_pairs(folder: Path) -> list[tuple[str, Path, Path]]:
    from stereopath.device.errors import CalibrationError

    if not folder.is_dir():
        raise CalibrationError(f"image folder not found: {folder}")
    lefts: dict[str, Path] = {}
    rights: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_EXTS:
            continue
        m = re.fullmatch(r"(left|right)(.*)", p.stem, flags=re.IGNORECASE)
        if m:
            (lefts if m.group(1).lower() == "left" else rights)[m.group(2)] = p
    keys = sorted(set(lefts) & set(rights))
    if not keys:
        raise CalibrationError(f"{folder}: no left*/right* image pairs found")
    return [(k, lefts[k], rights[k]) for k in keys]


def plot_path(args: argparse.Namespace) -> Path | None:
    """--plot, or beside --out; None with --no-plot or neither."""
    if args.no_plot:
        return None
    if args.plot:
        return Path(args.plot)
    if args.out:
        from stereopath.device.commands.calibration_plots import default_plot_path

        return default_plot_path(args.out, "reprojection")
    return None


def run(args: argparse.Namespace) -> int:
    import cv2

    from stereopath.device.core.calibration import calibrate_stereo, find_corners, parse_board
    from stereopath.device.errors import CalibrationError
    from stereopath.device.formats.rig_files import save_rig_yaml

    from stereopath.device.formats.fileio import check_out_file

    board = parse_board(args.board)
    if args.square_mm <= 0:
        raise CalibrationError(f"--square-mm must be positive, got {args.square_mm}")
    if args.out:
        check_out_file(args.out, example="rig.yaml")  # before the corners are searched in every pair
    plot = plot_path(args)
    if plot is not None:
        check_out_file(plot, option="--plot", example="reprojection.png")
    pairs = find_pairs(Path(args.images_dir))
    left_c, right_c, used, size = [], [], [], None
    for key, lp, rp in pairs:
        imgs = [cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)]
        for p, im in zip((lp, rp), imgs):
            if im is None:
                raise CalibrationError(f"cannot read image {p}")
        s = (imgs[0].shape[1], imgs[0].shape[0])
        if imgs[1].shape != imgs[0].shape or (size is not None and s != size):
            raise CalibrationError(f"pair {key}: image sizes differ from the others")
        size = s
        cl, cr = find_corners(imgs[0], board), find_corners(imgs[1], board)
        found = cl is not None and cr is not None
        print(f"  pair {key:>6}: {'board found' if found else 'board NOT found in ' + ('left' if cl is None else 'right')}")
        if found:
            left_c.append(cl)
            right_c.append(cr)
            used.append(key)
    res = calibrate_stereo(left_c, right_c, size, board, args.square_mm / 1000.0, name=args.name)
    print(f"pairs used: {res.pairs_used} of {len(pairs)}  image size {size[0]}x{size[1]}")
    print(f"RMS reprojection error: {res.rms_px:.3f} px (left alone {res.rms_left_px:.3f}, "
          f"right alone {res.rms_right_px:.3f})")
    print(f"baseline: {res.baseline_m * 1000:.2f} mm  T_cam1_cam0 = "
          f"[{', '.join(f'{v * 1000:.2f}' for v in res.rig.T)}] mm")
    if args.out:
        save_rig_yaml(res.rig, args.out, comment=(
            f"stereopath device calibrate-stereo {args.images_dir} --board {args.board} --square-mm {args.square_mm}\n"
            f"RMS reprojection error {res.rms_px:.3f} px over {res.pairs_used} pairs"))
        print(f"wrote {args.out}")
    if plot is not None:
        from stereopath.device.commands.calibration_plots import plot_reprojection

        why_not = plot_reprojection(plot, used, res.per_view_px, res.rms_px, args.max_rms)
        print(f"plot skipped: {why_not}" if why_not else f"wrote {plot}")
    if res.rms_px > args.max_rms:
        print(f"FAIL: RMS error {res.rms_px:.3f} px above --max-rms {args.max_rms}")
        return 1
    return 0
