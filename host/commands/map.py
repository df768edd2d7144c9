"""Dense 3D model of a recorded session or of keyframes stored by `host live`.

SESSION_OR_KEYFRAMES_DIR is a session folder (with mav0/; poses from its trajectory.tum, or
--poses FILE) or a keyframes folder written by `host live` (kf_*.msgpack + index.csv; the rig
calibration comes from a rig.yaml beside them or --rig).  Stereo depth (semi-global matching with
a left-right check) of each keyframe is fused into a TSDF volume; OUT gets mesh.ply, cloud.ply,
model.png (a rendered preview) and map.json (counts, voxel size, timings, and preset_choice: which
preset was used and why).  --preset auto (the default) chooses object, room or large_room from a
survey of a few keyframes' stereo depth: object when the surfaces within 2 m are a good share of
the view and at most 1.6 m across, else room or large_room by how far the scene reaches.  Nothing is
written when the input is unusable.
"""

from __future__ import annotations

import argparse
import sys

from stereopath.device.commands.arg_types import finite_number

# stereopath.host.mapping.mapper.PRESET_CHOICES without importing the mapper (a test checks)
MAP_PRESET_CHOICES = ("auto", "object", "room", "large_room")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", metavar="SESSION_OR_KEYFRAMES_DIR", help="session folder or stored keyframes folder")
    p.add_argument("--out", required=True, help="output folder (created; existing model files are replaced)")
    p.add_argument("--preset", default="auto", choices=MAP_PRESET_CHOICES,
                   help="depth range, voxel size and keyframe spacing: object scans (0.25-2 m, 4 mm), rooms "
                        "(0.4-6 m, 2 cm), large rooms (0.5-15 m, 5 cm), or auto: chosen from the keyframes' stereo "
                        "depth (the choice and why in map.json) (default: auto)")
    p.add_argument("--voxel-mm", type=finite_number("millimetres", allow_minimum=False), default=None, help="TSDF voxel size in mm (default from the preset)")
    p.add_argument("--poses", default=None, help="TUM or KITTI pose file to use instead of trajectory.tum")
    p.add_argument("--rig", default=None, help="rig YAML for stored keyframes (default: rig.yaml beside them)")
    p.add_argument("--stride", type=int, default=None,
                   help="every N-th posed frame is a keyframe (default: by pose change)")
    p.add_argument("--max-keyframes", type=int, default=None, help="use at most this many keyframes (evenly)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame or keyframe (default: skip it, counted in map.json)")


def run(args: argparse.Namespace) -> int:
    from stereopath.host.mapping.mapper import map_path

    from stereopath.device.formats.fileio import check_out_folder

    check_out_folder(args.out)
    changes = {}
    if args.stride is not None:
        changes["stride"] = args.stride
    if args.max_keyframes is not None:
        changes["max_keyframes"] = args.max_keyframes
    result = map_path(args.input, args.out, args.preset, poses=args.poses, rig=args.rig,
                      progress=False if args.no_progress else None, strict=bool(getattr(args, "strict", False)),
                      voxel_mm=args.voxel_mm, **changes)
    s = result.stats
    c = s["preset_choice"]
    if c.get("asked") == "auto":
        print(f"preset {c['preset']} (auto: {c['reason']})")
    t = s["timings_s"]
    print(f"{s['keyframes']} keyframes ({s['frames_total']} frames), voxel {s['voxel_mm']:.1f} mm: "
          f"mesh {s['mesh_vertices']} vertices / {s['mesh_triangles']} triangles, cloud {s['cloud_points']} points")
    print(f"depth {t['depth']:.1f} s ({s['depth_ms_per_keyframe']:.0f} ms/keyframe), fusion {t['fusion']:.1f} s, "
          f"total {t['total']:.1f} s -> {args.out}/mesh.ply, cloud.ply, model.png, map.json")
    if s.get("keyframes_skipped"):
        print(f"warning: skipped {s['keyframes_skipped']} unreadable keyframe(s) (listed in map.json; "
              f"--strict stops instead)", file=sys.stderr)
    return 0
