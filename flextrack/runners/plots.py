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
    rows = record.scored()
    t0 = record.rows[0].t_ns if record.rows else 0
    t = np.array([(r.t_ns - t0) * 1e-9 for r in rows])
    fig, (ax_px, ax_pos) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    ax_px.plot(t, [r.proj_px for r in rows], lw=0.8, color="tab:blue")
    bad = [r for r in rows if r.status != "FINE"]
    if bad:
        ax_px.scatter([(r.t_ns - t0) * 1e-9 for r in bad], [r.proj_px for r in bad], s=6, color="tab:red",
                      label="not FINE", zorder=3)
        ax_px.legend(loc="upper right")
    ax_px.set_ylabel("2D projection error [px]")
    ax_px.set_title(title or "tracking error")
    ax_px.grid(alpha=0.3)
    ax_pos.plot(t, [r.pos_mm for r in rows], lw=0.8, color="tab:green", label="position [mm]")
    ax_pos.plot(t, [r.ori_deg * 10 for r in rows], lw=0.8, color="tab:orange", label="orientation [0.1 deg]")
    ax_pos.set_xlabel("time [s]")
    ax_pos.legend(loc="upper right")
    ax_pos.grid(alpha=0.3)
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
