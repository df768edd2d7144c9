"""What COLMAP makes of a `host export --format colmap` model: its own bundle adjustment from our
poses, and its own point triangulation (SIFT, exhaustive matching, `triangulate_points`) from our
poses on the exported images.

    python benchmarks/bench_colmap_export.py REPROCESSED_OUT [--work DIR]

Prints: our bundle adjustment's RMS and pycolmap's on the exported model; how far pycolmap's bundle
adjustment (calibration and rig held; then with the focal lengths and principal points free) moves
the cameras; COLMAP's triangulated points from our poses: count, mean track length, mean reprojection
error, and the distance of its points to ours (the nearest of our points).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _centres(rec) -> dict[int, np.ndarray]:
    return {i: im.projection_center().copy() for i, im in rec.images.items()}


def _ba_moves(model: Path, free_intrinsics: bool) -> tuple[float, float, float]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(model))
    before = _centres(rec)
    o = pycolmap.BundleAdjustmentOptions()
    o.refine_focal_length = o.refine_principal_point = free_intrinsics
    o.refine_extra_params = False
    o.refine_sensor_from_rig = False
    o.print_summary = False
    t0 = time.perf_counter()
    pycolmap.bundle_adjustment(rec, o)
    d = np.array([np.linalg.norm(im.projection_center() - before[i]) for i, im in rec.images.items()])
    return float(d.max()), float(np.median(d)), time.perf_counter() - t0


def _triangulate(export: Path, work: Path) -> dict:
    import pycolmap
    from scipy.spatial import cKDTree

    ours = pycolmap.Reconstruction(str(export / "sparse" / "0"))
    db_path = work / "database.db"
    db = pycolmap.Database.open(str(db_path))
    for cam in ours.cameras.values():
        db.write_camera(cam, use_camera_id=True)
    for rig in ours.rigs.values():
        db.write_rig(rig, use_rig_id=True)
    for im in ours.images.values():
        db.write_image(pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id), use_image_id=True)
    for fr in ours.frames.values():
        f = pycolmap.Frame(frame_id=fr.frame_id, rig_id=fr.rig_id)
        for d in fr.data_ids:
            f.add_data_id(d)
        db.write_frame(f, use_frame_id=True)
    db.close()
    t0 = time.perf_counter()
    pycolmap.extract_features(str(db_path), str(export / "images"), image_names=[im.name for im in ours.images.values()],
                              device=pycolmap.Device.cpu)
    t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(str(db_path), device=pycolmap.Device.cpu)
    t_match = time.perf_counter() - t0
    out = work / "triangulated"
    out.mkdir()
    t0 = time.perf_counter()
    tri = pycolmap.triangulate_points(ours, str(db_path), str(export / "images"), str(out))
    t_tri = time.perf_counter() - t0
    ref = pycolmap.Reconstruction(str(export / "sparse" / "0"))
    ours_xyz = np.array([p.xyz for p in ref.points3D.values()])
    xyz = np.array([p.xyz for p in tri.points3D.values()]).reshape(-1, 3)
    dist = cKDTree(ours_xyz).query(xyz)[0] if len(xyz) else np.zeros(0)
    lengths = [p.track.length() for p in tri.points3D.values()]
    return {"points": len(xyz), "mean_track_length": float(np.mean(lengths)) if lengths else 0.0,
            "mean_reprojection_error_px": tri.compute_mean_reprojection_error(),
            "nearest_of_ours_median_mm": float(np.median(dist) * 1e3) if len(dist) else float("nan"),
            "nearest_of_ours_p90_mm": float(np.quantile(dist, 0.9) * 1e3) if len(dist) else float("nan"),
            "seconds": {"extract": round(t_extract, 1), "match": round(t_match, 1), "triangulate": round(t_tri, 1)}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("result", help="a `host reprocess` output folder")
    ap.add_argument("--work", default=None, help="working folder (default: a temporary one, removed)")
    args = ap.parse_args(argv)
    import json

    import pycolmap

    from stereopath.host.export.run import export_result

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench-colmap-"))
    try:
        export = work / "colmap"
        summary = export_result(args.result, export, "colmap", force=True, progress=False)
        rep = json.loads((Path(args.result) / "report.json").read_text())
        rec = pycolmap.Reconstruction(str(export / "sparse" / "0"))
        ate = "n/a" if rep.get("ate_rmse_m") is None else f"{rep['ate_rmse_m'] * 1e3:.3f} mm"
        print(f"exported: {summary['keyframes']} keyframes, {summary['points']} points, {summary['observations']} "
              f"observations; our BA rms {summary['ba_rms_px']:.4f} px, COLMAP mean reprojection error "
              f"{rec.compute_mean_reprojection_error():.4f} px; path ATE {ate}")
        for free in (False, True):
            mx, med, s = _ba_moves(export / "sparse" / "0", free)
            print(f"pycolmap bundle adjustment ({'focal lengths and principal points free' if free else 'calibration and rig held'}): "
                  f"cameras move max {mx * 1e3:.4f} mm, median {med * 1e3:.4f} mm ({s:.1f} s)")
        tri_work = work / "tri"
        tri_work.mkdir(exist_ok=True)
        t = _triangulate(export, tri_work)
        print(f"COLMAP triangulation from our poses (SIFT, exhaustive matching): {t['points']} points, mean track "
              f"length {t['mean_track_length']:.2f}, mean reprojection error {t['mean_reprojection_error_px']:.3f} px; "
              f"distance to the nearest of our points: median {t['nearest_of_ours_median_mm']:.2f} mm, "
              f"90 % {t['nearest_of_ours_p90_mm']:.2f} mm; seconds {t['seconds']}")
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
