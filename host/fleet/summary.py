"""The fleet summary: ``DIR/fleet.json`` (machine-readable) and ``DIR/fleet.html`` (a table).

Per session: status, attempts, node, stages, ATE after (and before) bundle adjustment when the
session has ground truth, frames, keyframes, mesh size, wall and CPU time, and the error of a
failed session.  Both files are rewritten atomically whenever a session finishes.
"""

from __future__ import annotations

import dataclasses
import html
import time
from pathlib import Path
from collections.abc import Mapping
from typing import Any

from stereopath.device.formats.fileio import write_json_atomic, write_text_atomic
from stereopath.host.evaluation.report import JsonValue
from stereopath.host.fleet.state import FleetResult, ReprocessSettings

FORMAT = "stereopath-fleet"
VERSION = 1

_ROW_KEYS = ("frames", "keyframes", "ate_rmse_m", "ate_reestimated_m", "mesh_vertices", "mesh_triangles",
             "mesh_bytes", "map_error", "stages", "stage_seconds", "wall_s", "cpu_s")


def summary_dict(result: FleetResult, settings: ReprocessSettings | Mapping[str, object]) -> dict[str, Any]:
    """``fleet.json``'s content from a :class:`stereopath.host.fleet.state.FleetResult`."""
    rows = []
    for st in result.sessions:
        r = st.result or {}
        row: dict[str, Any] = {"id": st.session.id, "session": str(st.session.path), "out": str(st.out),
                               "status": st.status, "attempts": st.attempts, "node": st.node,
                               "stored_stages": list(st.stored), "error": st.error}
        row.update({k: r.get(k) for k in _ROW_KEYS})
        if row["wall_s"] is None and st.started and st.finished:
            row["wall_s"] = round(st.finished - st.started, 3)
        rows.append(row)
    return {
        "format": FORMAT, "version": VERSION,
        "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "interrupted": bool(result.interrupted),
        "wall_s": round(result.wall_s, 3),
        "counts": result.counts(),
        "cluster": result.cluster,
        "settings": dataclasses.asdict(settings) if dataclasses.is_dataclass(settings) else dict(settings),
        "sessions": rows,
    }


def _cell(v: JsonValue, scale: float = 1.0, digits: int = 3) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, float) or scale != 1.0:
        return f"{float(v) * scale:.{digits}f}"
    return html.escape(str(v))


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; }
td.l, th.l { text-align: left; }
th { background: #f0f0f0; }
.done { color: #185; } .failed { color: #b22; font-weight: bold; } .interrupted, .pending, .running { color: #a60; }
.note { color: #666; font-size: 0.9em; }
"""


def render_html(summary: dict[str, Any]) -> str:
    """``fleet.html``: counts, cluster, and one row per session linking its ``report.html``."""
    c = summary["counts"]
    cl = summary.get("cluster") or {}
    head = ["session", "status", "attempts", "node", "frames", "keyframes", "ATE before BA (mm)",
            "ATE after BA (mm)", "mesh vertices", "mesh (MB)", "wall (s)", "CPU (s)", "note"]
    rows = []
    for r in summary["sessions"]:
        sid = html.escape(r["id"])
        link = f"<a href='{html.escape(r['id'])}/report.html'>{sid}</a>" if r["status"] == "done" else sid
        note = r.get("error") or r.get("map_error") or ""
        if r["status"] in ("running", "interrupted", "pending") and r.get("stored_stages"):
            note = "stored: " + ", ".join(r["stored_stages"])
        cells = [link, f"<span class='{html.escape(r['status'])}'>{html.escape(r['status'])}</span>",
                 _cell(r.get("attempts")), _cell(r.get("node")), _cell(r.get("frames")), _cell(r.get("keyframes")),
                 _cell(r.get("ate_reestimated_m"), 1000.0), _cell(r.get("ate_rmse_m"), 1000.0),
                 _cell(r.get("mesh_vertices")), _cell(r.get("mesh_bytes"), 1e-6, 1),
                 _cell(r.get("wall_s"), 1.0, 1), _cell(r.get("cpu_s"), 1.0, 1), html.escape(note)]
        cls = ["l", "l", "", "l"] + [""] * 8 + ["l"]
        rows.append("<tr>" + "".join(f"<td class='{k}'>{v}</td>" if k else f"<td>{v}</td>"
                                     for k, v in zip(cls, cells)) + "</tr>")
    th = "".join(f"<th class='l'>{html.escape(h)}</th>" if i in (0, 1, 3, 12) else f"<th>{html.escape(h)}</th>"
                 for i, h in enumerate(head))
    s = summary.get("settings") or {}
    title = "stereopath fleet reprocessing"
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{title}</title><style>{_CSS}</style>"
            f"</head><body><h1>{title}</h1>"
            f"<p>{c.get('done', 0)} done, {c.get('failed', 0)} failed, {c.get('running', 0)} running, "
            f"{c.get('interrupted', 0)} interrupted, {c.get('pending', 0)} pending"
            f"{' (the run was interrupted: run the same command again to resume)' if summary.get('interrupted') else ''}"
            f"; wall time {summary['wall_s']:.1f} s.</p>"
            f"<p class='note'>Ray {html.escape(str(cl.get('address')))}: {_cell(cl.get('nodes'))} node(s), "
            f"{_cell(cl.get('cpus'))} CPUs, {_cell(cl.get('max_in_flight'))} sessions at a time "
            f"({_cell(cl.get('task_cpus'))} CPU and {_cell(cl.get('task_memory_gb'))} GB each). Preset "
            f"{html.escape(str(s.get('preset')))}, map {'on (' + html.escape(str(s.get('map_preset'))) + ')' if s.get('do_map') else 'off'}."
            f" Written {html.escape(summary['written_utc'])}.</p>"
            f"<table><tr>{th}</tr>{''.join(rows)}</table></body></html>\n")


def write_summary(out_dir: Path, result: FleetResult,
                  settings: ReprocessSettings | Mapping[str, object]) -> dict[str, Any]:
    """Write ``fleet.json`` and ``fleet.html`` into ``out_dir``; returns the summary dict."""
    summary = summary_dict(result, settings)
    # no fsync: the summary is rewritten after every change and can be rebuilt by rerunning the command
    write_json_atomic(out_dir / "fleet.json", summary, fsync=False)
    write_text_atomic(out_dir / "fleet.html", render_html(summary), fsync=False)
    return summary
