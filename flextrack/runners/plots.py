"""PNG plots of one tracking run: 2D error over time (with the status) and the trajectory."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from flextrack.geometry import se3
from flextrack.runners.results import TrackRecord


def plot_error(record: TrackRecord, path: str | Path, title: str = "") -> Path:
    """2D, position and orientation error over time on a log axis (errors span 0.01 to 1000 px on a recording
    that leaves the view), with a gap wherever nothing was scored (out of view, no estimate yet) and the
    frames the tracker did not call FINE marked."""
    record.scored()  # fills in the errors
    rows = list(record.rows)
    t0 = rows[0].t_ns if rows else 0
    t = np.array([(r.t_ns - t0) * 1e-9 for r in rows])
    scored = np.array([r.T_CO is not None and r.T_gt is not None for r in rows], dtype=bool)

    def series(key: str, scale: float = 1.0) -> np.ndarray:  # NaN where not scored: the line breaks there
        return np.array([getattr(r, key) * scale if ok else np.nan for r, ok in zip(rows, scored)], dtype=float)

    fig, (ax_px, ax_pos) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    ax_px.plot(t, series("proj_px"), lw=0.8, color="tab:blue", label="2D error")
    bad = [r for r, ok in zip(rows, scored) if ok and r.status != "FINE"]
    if bad:
        ax_px.scatter([(r.t_ns - t0) * 1e-9 for r in bad], [r.proj_px for r in bad], s=6, color="tab:red",
                      label=f"not FINE ({len(bad)})", zorder=3)
    if scored.any() and not scored.all():
        ax_px.plot([], [], " ", label=f"gaps: not scored ({int((~scored).sum())} frames)")
    ax_px.set_yscale("log")
    ax_px.set_ylabel("2D projection error [px]")
    ax_px.set_title(title or "tracking error")
    ax_px.grid(alpha=0.3, which="both")
    ax_px.legend(loc="upper right", fontsize=8)
    ax_pos.plot(t, series("pos_mm"), lw=0.8, color="tab:green", label="position [mm]")
    ax_pos.plot(t, series("ori_deg", 10.0), lw=0.8, color="tab:orange", label="orientation [0.1 deg]")
    ax_pos.set_yscale("log")
    ax_pos.set_xlabel("time [s]")
    ax_pos.legend(loc="upper right", fontsize=8)
    ax_pos.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_trajectory(record: TrackRecord, path: str | Path, title: str = "") -> Path:
    """The camera's position in the object frame (T_OC), estimate against ground truth, top and side."""
    rows = record.scored()
    est = np.array([se3.inverse(r.T_CO)[:3, 3] for r in rows]).reshape(-1, 3)
    gt = np.array([se3.inverse(r.T_gt)[:3, 3] for r in rows]).reshape(-1, 3)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, (i, j), name in zip(axes, ((0, 1), (0, 2)), ("x-y", "x-z")):
        ax.plot(gt[:, i], gt[:, j], lw=2.0, color="0.6", label="ground truth")
        ax.plot(est[:, i], est[:, j], lw=0.8, color="tab:blue", label="tracker")
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_title(f"camera in the object frame ({name})")
        ax.axis("equal")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
