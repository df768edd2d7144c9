"""A self-contained HTML page for a reprocessing report, and its error-over-distance figure.

:func:`write_html_report` turns a ``report.json`` dict (the :mod:`stereopath.host.evaluation.report` schema plus
``extra.before_after``) into ``report.html``: a summary table, the before/after table (on-board,
re-estimated, bundle adjusted), bundle-adjustment and stage figures, and the images linked by
relative paths (they sit beside the page).  No scripts, no external resources.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.formats.fileio import replacing, write_text_atomic
from stereopath.device.formats.tum import Trajectory

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 4px 10px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f0f0f0; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.5em 0; }
.note { color: #666; font-size: 0.9em; }
"""


def _fmt(v: Any, scale: float = 1.0, digits: int = 3, unit: str = "") -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)) and scale == 1.0:
        return f"{int(v)}{unit}"
    try:
        return f"{float(v) * scale:.{digits}f}{unit}"
    except (TypeError, ValueError):
        return html.escape(str(v))


def _table(headers: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def render_html(report: dict[str, Any], images: list[str], title: str = "stereopath reprocessing report") -> str:
    """The page as a string (see the module doc); ``images`` are paths relative to the page."""
    extra = report.get("extra") or {}
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    parts.append(f"<p>Source <code>{html.escape(str(report.get('source')))}</code>, "
                 f"{_fmt(report.get('frames'))} frames ({_fmt(report.get('frames_tracked'))} tracked), "
                 f"world frame {html.escape(str(report.get('world_frame')))}, preset "
                 f"<b>{html.escape(str((extra.get('preset') or {}).get('name', '')))}</b>.</p>")
    ba_cmp = extra.get("before_after") or {}
    rows = []
    for key, name in (("onboard", "on-board (recorded)"), ("reestimated", "re-estimated"),
                      ("bundle_adjusted", "bundle adjusted (final)")):
        m = ba_cmp.get(key)
        if not m:
            missing = "not in the session" if key == "onboard" else "&ndash;"
            rows.append([name, missing] + ["&ndash;"] * 5)
            continue
        rows.append([name, _fmt(m.get("frames")), _fmt(m.get("ate_rmse_m"), 1000, 3, " mm"),
                     _fmt(m.get("end_error_m"), 1000, 3, " mm"), _fmt(m.get("rpe_trans_rmse_m"), 1000, 3, " mm"),
                     _fmt(m.get("rpe_rot_rmse_deg"), 1, 4, "&deg;"), _fmt(m.get("accuracy_pct"), 1, 3, " %")])
    parts.append("<h2>Path before and after</h2>")
    parts.append(_table(["path", "frames", "ATE RMSE", "end error", "RPE trans", "RPE rot", "accuracy"], rows))
    ratios = [(k, ba_cmp.get(k)) for k in ("ate_ratio_vs_onboard", "ate_ratio_vs_reestimated")]
    if any(v is not None for _, v in ratios):
        parts.append("<p>ATE ratio (after / before): " + ", ".join(
            f"{html.escape(k.replace('ate_ratio_', '').replace('_', ' '))} <b>{_fmt(v, 1, 3)}</b>"
            for k, v in ratios if v is not None) + "</p>")
    elif not any((ba_cmp.get(k) or {}).get("ate_rmse_m") is not None for k in ("reestimated", "bundle_adjusted")):
        parts.append("<p class='note'>No ground truth in this session: errors cannot be computed.</p>")
    for img in images:
        parts.append(f"<p><img src='{html.escape(img)}' alt='{html.escape(img)}'></p>")
    bundle = extra.get("bundle_adjustment") or {}
    tracks = extra.get("tracks") or {}
    if bundle or tracks:
        parts.append("<h2>Tracks and bundle adjustment</h2>")
        rows = [[html.escape(k.replace("_", " ")), _fmt(v)] for k, v in {**tracks, **bundle}.items()
                if not isinstance(v, (dict, list))]
        parts.append(_table(["quantity", "value"], rows))
    rr = extra.get("rig_refined")
    if rr:
        cx, f = rr["cam1_cx_px"], html.escape(str(rr["file"]))
        parts.append(f"<p>Refined stereo calibration: <a href='{f}'>{f}</a> (right principal point cx "
                     f"{_fmt(cx['before'], 1, 4)} &rarr; {_fmt(cx['after'], 1, 4)} px): for later sessions of this "
                     "rig (device configuration source.rig_file).</p>")
    stages = extra.get("stages") or {}
    if stages:
        parts.append("<h2>Stages</h2>")
        parts.append(_table(["stage", "status", "time (s)"],
                            [[html.escape(k), html.escape(str(v.get("status"))), _fmt(v.get("seconds"), 1, 1)]
                             for k, v in stages.items()]))
    mp = extra.get("map")
    if mp and mp.get("error"):
        parts.append(f"<h2>Model</h2><p>The dense model failed: {html.escape(str(mp['error']))}</p>")
    elif mp:
        keys = ("keyframes", "voxel_mm", "mesh_vertices", "mesh_triangles", "cloud_points")
        parts.append("<h2>Model</h2>")
        parts.append(_table(["quantity", "value"], [[k.replace("_", " "), _fmt(mp.get(k))] for k in keys if k in mp]))
        parts.append("<p>Files: <a href='mesh.ply'>mesh.ply</a>, <a href='cloud.ply'>cloud.ply</a>, "
                     "<a href='map.json'>map.json</a>.</p>")
    parts.append("<p class='note'>Also here: <a href='trajectory.tum'>trajectory.tum</a> (refined path), "
                 "<a href='report.json'>report.json</a>.</p></body></html>\n")
    return "".join(parts)


def write_html_report(path: str | Path, report: dict[str, Any], images: list[str],
                      title: str = "stereopath reprocessing report") -> None:
    """Write :func:`render_html` to ``path`` atomically."""
    write_text_atomic(path, render_html(report, images, title), fsync=False)


def plot_errors(path_png: str | Path, gt: Trajectory, paths: dict[str, Trajectory], max_diff_s: float = 0.01) -> bool:
    """Aligned position error over distance travelled for each of ``paths``; False when none associates."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from evo.core.geometry import GeometryException

    from stereopath.device.errors import StereopathError
    from stereopath.host.evaluation.evaluate import associate_and_align, position_errors

    fig = Figure(figsize=(8, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    curves = []
    for name, traj in paths.items():
        try:
            curves.append((name, *position_errors(associate_and_align(gt, traj, max_diff_s))))
        except (StereopathError, GeometryException):
            continue
    if not curves:
        return False
    top = max(float(np.max(e, initial=0.0)) for _, _, e in curves)
    scale, unit = (1000.0, "mm") if top < 0.5 else (1.0, "m")
    for name, dist, err in curves:
        ax.plot(dist, err * scale, lw=1.2, label=f"{name} (RMSE {np.sqrt(np.mean(err ** 2)) * scale:.3g} {unit})")
    ax.set_ylabel(f"aligned position error ({unit})")
    ax.set_xlabel("distance along the ground truth (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    with replacing(path_png) as tmp:
        fig.savefig(tmp)
    return True
