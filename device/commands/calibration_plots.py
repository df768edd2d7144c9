"""The calibration commands' figures: reprojection error per view, and the IMU's still window.

matplotlib is optional on the device: each function returns False (and writes nothing) when it
cannot be imported, and the command carries on.  Rendering uses the Agg canvas directly (no
display, no global backend); the file is replaced atomically.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

STANDARD_GRAVITY_M_S2 = 9.80665


def _figure(size: tuple[float, float]):
    """(Figure, None), or (None, the reason) when matplotlib is missing."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        return None, f"matplotlib is not installed ({exc})"
    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)
    return fig, None


def _save(fig, path: Path) -> None:
    from stereopath.device.formats.fileio import replacing

    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as tmp:
        fig.savefig(tmp, format="png")


def plot_reprojection(path: str | Path, pair_ids: list[str], per_view_px: np.ndarray, rms_px: float,
                      max_rms_px: float | None = None) -> str | None:
    """Bars of the RMS reprojection error of each pair (left and right camera) with the overall RMS.

    Returns None when written, otherwise why not (matplotlib missing).
    """
    per_view = np.asarray(per_view_px, dtype=float).reshape(len(pair_ids), -1)
    fig, why = _figure((max(6.0, 0.45 * len(pair_ids) + 3.0), 4.2))
    if fig is None:
        return why
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(pair_ids))
    width = 0.38
    ax.bar(x - width / 2, per_view[:, 0], width, label="left camera", color="tab:blue")
    if per_view.shape[1] > 1:
        ax.bar(x + width / 2, per_view[:, 1], width, label="right camera", color="tab:orange")
    ax.axhline(rms_px, color="k", lw=1.2, ls="--", label=f"stereo RMS {rms_px:.3f} px")
    if max_rms_px is not None:
        ax.axhline(max_rms_px, color="tab:red", lw=1.0, ls=":",
                   label=f"--max-rms {max_rms_px:g} px (limit on the stereo RMS)")
    ax.set_xticks(x)
    ax.set_xticklabels(pair_ids, rotation=45 if len(pair_ids) > 12 else 0)
    ax.set_xlabel("image pair")
    ax.set_ylabel("RMS reprojection error [px]")
    ax.set_title(f"Stereo calibration: reprojection error per view ({len(pair_ids)} pairs)")
    ax.set_ylim(0, max(float(per_view.max()), rms_px, max_rms_px or 0.0) * 1.25)
    ax.legend(loc="upper right", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    _save(fig, Path(path))
    return None


def plot_still_window(path: str | Path, t_ns: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                      window_ns: tuple[int, int], window_name: str,
                      frames_ns: tuple[int, int] | None = None) -> str | None:
    """Gyro and accelerometer norms over time with the still window used shaded.

    ``frames_ns``: the span of the recorded image frames, drawn as two dotted lines when given.
    Returns None when written, otherwise why not (matplotlib missing).
    """
    fig, why = _figure((9.0, 5.2))
    if fig is None:
        return why
    t_ns = np.asarray(t_ns, dtype=np.int64)
    origin = int(t_ns[0])
    t_s = (t_ns - origin) / 1e9
    gyro_deg_s = np.rad2deg(np.linalg.norm(np.asarray(gyro_rad_s, float).reshape(-1, 3), axis=1))
    accel = np.linalg.norm(np.asarray(accel_m_s2, float).reshape(-1, 3), axis=1)
    w0, w1 = ((int(w) - origin) / 1e9 for w in window_ns)
    ax_g = fig.add_subplot(2, 1, 1)
    ax_a = fig.add_subplot(2, 1, 2, sharex=ax_g)
    ax_g.plot(t_s, gyro_deg_s, lw=0.8, color="tab:blue")
    ax_g.set_ylabel("|gyro| [deg/s]")
    ax_a.plot(t_s, accel, lw=0.8, color="tab:green")
    ax_a.axhline(STANDARD_GRAVITY_M_S2, color="k", lw=0.8, ls="--", label="standard gravity 9.80665")
    ax_a.set_ylabel("|accel| [m/s²]")
    ax_a.set_xlabel("time since the first IMU sample [s]")
    for ax in (ax_g, ax_a):
        ax.axvspan(w0, w1, color="tab:orange", alpha=0.25, label=f"still window ({window_name})")
        if frames_ns is not None:
            for k, f in enumerate(frames_ns):
                ax.axvline((int(f) - origin) / 1e9, color="0.4", lw=0.9, ls=":",
                           label="first / last image frame" if k == 0 else None)
        ax.grid(alpha=0.3)
    ax_a.legend(loc="upper right", fontsize=8)
    ax_g.legend(loc="upper right", fontsize=8)
    ax_g.set_title(f"IMU calibration: still window {w0:.2f}-{w1:.2f} s "
                   f"({int(np.count_nonzero((t_ns >= window_ns[0]) & (t_ns <= window_ns[1])))} samples)")
    fig.tight_layout()
    _save(fig, Path(path))
    return None


def default_plot_path(out: str | Path, what: str) -> Path:
    """``rig.yaml`` -> ``rig_<what>.png`` beside it."""
    p = Path(out)
    return p.with_name(f"{p.stem}_{what}.png")
