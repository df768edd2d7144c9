"""``report.json``: one schema for every run of an estimator on a sequence.

Keys (always all present, in this order)::

    source, estimator, frames, frames_tracked, path_length_m, end_error_m, end_error_pct,
    ate_rmse_m, rpe_trans_rmse_m, rpe_rot_rmse_deg, accuracy_pct, median_frame_ms,
    p95_frame_ms, world_frame

plus an optional ``extra`` mapping for anything else.  Error fields are ``null`` when the
sequence has no ground truth; frame times are the estimator's work per stereo frame only.
``world_frame`` is ``first_camera`` or ``gravity_aligned``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, SupportsFloat, Union

import numpy as np

from stereopath.device.formats.fileio import load_json, write_text_atomic

REPORT_KEYS = (
    "source",
    "estimator",
    "frames",
    "frames_tracked",
    "path_length_m",
    "end_error_m",
    "end_error_pct",
    "ate_rmse_m",
    "rpe_trans_rmse_m",
    "rpe_rot_rmse_deg",
    "accuracy_pct",
    "median_frame_ms",
    "p95_frame_ms",
    "world_frame",
)
METRIC_KEYS = ("path_length_m", "end_error_m", "end_error_pct", "ate_rmse_m", "rpe_trans_rmse_m",
               "rpe_rot_rmse_deg", "accuracy_pct")
WORLD_FRAMES = ("first_camera", "gravity_aligned")
# a value JSON holds (what json.loads returns, what json.dumps takes)
JsonValue = Union[None, bool, int, float, str, list["JsonValue"], dict[str, "JsonValue"]]


def _num(v: SupportsFloat | None) -> float | None:
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _plain(v: object) -> JsonValue:
    """numpy scalars/arrays and non-finite floats -> JSON-safe Python values."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _num(v)
    return v


def make_report(source: str, estimator: str, frames: int, frames_tracked: int, metrics: dict[str, Any] | None,
                frame_ms: list[float] | np.ndarray, world_frame: str,
                extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Build the report dict.  ``metrics`` is :func:`stereopath.host.evaluation.evaluate.evaluate`'s result or None."""
    if world_frame not in WORLD_FRAMES:
        raise ValueError(f"world_frame must be one of {WORLD_FRAMES}, got {world_frame!r}")
    ms = np.asarray(list(frame_ms), dtype=float)
    ms = ms[np.isfinite(ms)]
    rep: dict[str, Any] = {
        "source": str(source),
        "estimator": str(estimator),
        "frames": int(frames),
        "frames_tracked": int(frames_tracked),
    }
    for key in METRIC_KEYS:
        rep[key] = _num(metrics.get(key)) if metrics else None
    rep["median_frame_ms"] = float(np.median(ms)) if ms.size else None
    rep["p95_frame_ms"] = float(np.percentile(ms, 95)) if ms.size else None
    rep["world_frame"] = world_frame
    if extra:
        rep["extra"] = _plain(extra)
    return {k: rep[k] for k in (*REPORT_KEYS, *(("extra",) if extra else ()))}


def write_report(path: str | Path, report: dict[str, Any]) -> None:
    """Write the report as JSON atomically (temp file + rename)."""
    missing = [k for k in REPORT_KEYS if k not in report]
    if missing:
        raise ValueError(f"report lacks key(s) {', '.join(missing)}")
    p = Path(path)
    text = json.dumps(_plain(report), indent=2, allow_nan=False) + "\n"
    write_text_atomic(p, text, fsync=False)


def read_report(path: str | Path) -> dict[str, Any]:
    from stereopath.device.errors import DatasetError

    p = Path(path)
    try:
        data = load_json(p)
    except FileNotFoundError:
        raise DatasetError(f"report not found: {p}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{p}: invalid JSON: {exc}") from None
    missing = [k for k in REPORT_KEYS if k not in data] if isinstance(data, dict) else list(REPORT_KEYS)
    if missing:
        raise DatasetError(f"{p}: not a stereopath report (missing {', '.join(missing)})")
    return data
