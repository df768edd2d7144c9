"""``path.png``: top view of the estimated path against ground truth, and error against distance.

The estimate is aligned onto the ground truth exactly as for the ATE (Umeyama SE(3), no scale;
:func:`stereopath.host.evaluation.evaluate.associate_and_align`).  The top view is the x-y plane of a gravity-aligned
world (z up), otherwise the plane of the two principal axes of the path.  Rendering uses the Agg
canvas directly, so no display and no global matplotlib backend are needed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereopath.device.formats.fileio import replacing
from stereopath.device.formats.tum import Trajectory


def _plane(points: np.ndarray, world_frame: str | None) -> tuple[np.ndarray, tuple[str, str]]:
    """(2x3 projection, axis labels) for the top view."""
    if world_frame == "gravity_aligned":
        return np.array([[1.0, 0, 0], [0, 1.0, 0]]), ("x [m]", "y [m]")
    c = points - points.mean(axis=0)
    if len(points) < 3 or not np.any(c):
        return np.array([[1.0, 0, 0], [0, 0, 1.0]]), ("x [m]", "z [m]")
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    axes = vt[:2].copy()
    for a in axes:  # deterministic sign: largest component positive
        if a[np.argmax(np.abs(a))] < 0:
            a *= -1
    return axes, ("principal axis 1 [m]", "principal axis 2 [m]")


def plot_path(path_png: str | Path, gt: Trajectory | None, est: Trajectory, world_frame: str | None = None,
              max_diff_s: float = 0.01, title: str | None = None) -> None:
    """Write the figure to ``path_png`` (atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from stereopath.host.evaluation.evaluate import associate_and_align, position_errors

    assoc = None
    if gt is not None:
        assoc = associate_and_align(gt, est, max_diff_s)
    fig = Figure(figsize=(11, 5) if assoc else (6, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if assoc else 1, 1)
    if assoc is not None:
        t0, t1 = assoc.gt.t_ns[0], assoc.gt.t_ns[-1]
        keep = (gt.t_ns >= t0) & (gt.t_ns <= t1)
        p_gt = gt.positions[keep]
        p_est = (assoc.T_gt_est @ est.T_world_cam)[:, :3, 3]
        P, labels = _plane(p_gt, world_frame)
        g2, e2 = p_gt @ P.T, p_est @ P.T
        ax.plot(g2[:, 0], g2[:, 1], "k-", lw=1.5, label="ground truth")
        ax.plot(e2[:, 0], e2[:, 1], "-", color="tab:red", lw=1.2, label="estimate (aligned)")
        ax.plot(g2[:1, 0], g2[:1, 1], "ko", ms=5, label="start")
    else:
        p_est = est.positions
        P, labels = _plane(p_est, world_frame)
        e2 = p_est @ P.T
        ax.plot(e2[:, 0], e2[:, 1], "-", color="tab:red", lw=1.2, label="estimate")
        ax.plot(e2[:1, 0], e2[:1, 1], "ko", ms=5, label="start")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("top view")
    if assoc is not None:
        dist, err = position_errors(assoc)
        ax2 = fig.add_subplot(1, 2, 2)
        ax2.plot(dist, err * 1000.0, "-", color="tab:blue", lw=1.2)
        rmse = float(np.sqrt(np.mean(err**2)))
        ax2.set_title(f"position error after alignment (ATE RMSE {rmse * 1000:.1f} mm)")
        ax2.set_xlabel("distance travelled along ground truth [m]")
        ax2.set_ylabel("position error [mm]")
        ax2.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    p = Path(path_png)
    with replacing(p) as tmp:
        fig.savefig(tmp, format="png")
