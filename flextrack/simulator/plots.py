"""Pictures of a sequence folder for a person to check at a glance (matplotlib, Agg backend).

- trajectory.png: the camera path from above and from the side, with the object and the
  viewing direction every second;
- imu.png: gyro and accelerometer against time, the still period shaded;
- allan.png (static sequences): the Allan deviation of gyro and accel beside the densities.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from flextrack.formats.sequence import Sequence, load
from flextrack.geometry import se3
from flextrack.simulator.render import load_model
from flextrack.simulator.statistics import allan_deviation, expected_adev


def _camera_poses(seq: Sequence) -> tuple[np.ndarray, np.ndarray]:
    times, T_CO = seq.gt_times_and_poses()
    return times, seq.T_WO[None] @ np.linalg.inv(T_CO)


def plot_trajectory(seq: Sequence, path: Path) -> Path:
    times, T_WC = _camera_poses(seq)
    object_W = se3.transform_points(seq.T_WO, np.asarray(load_model(seq.model_path).vertices))
    p = T_WC[:, :3, 3]
    step = max(1, round(len(times) / max(1.0, (times[-1] - times[0]) / 1e9)))  # one arrow a second
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    for ax, (i, j), label in zip(axes, ((0, 1), (0, 2)), ("top view (x, y)", "side view (x, z)")):
        ax.scatter(object_W[::20, i], object_W[::20, j], s=1, c="tab:red", label="object")
        sc = ax.scatter(p[:, i], p[:, j], c=(times - times[0]) / 1e9, s=2, cmap="viridis")
        view = T_WC[::step, :3, 2] * 0.15
        ax.quiver(p[::step, i], p[::step, j], view[:, i], view[:, j], angles="xy", scale_units="xy", scale=1,
                  width=0.003, color="0.3")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    fig.colorbar(sc, ax=axes, label="time [s]")
    axes[0].legend(loc="upper right")
    placement = seq.meta.get("placement")
    if placement:  # a converted recording: where the virtual object went, and how often it is seen whole
        centre = placement["centre_W"]
        label = (f"object centre ({placement.get('how', 'auto')}): ({centre[0]:.2f}, {centre[1]:.2f}, "
                 f"{centre[2]:.2f}) m, seen whole in {100 * placement['visible_fraction']:.0f} % of frames")
        for ax, (i, j) in zip(axes, ((0, 1), (0, 2))):
            ax.scatter([centre[i]], [centre[j]], marker="*", s=200, c="tab:red", edgecolors="k", zorder=5,
                       label=label)
        axes[0].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{seq.name}: camera trajectory (arrows: viewing direction, 1 s apart)")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_imu(seq: Sequence, path: Path) -> Path:
    t = (seq.imu.t_ns - seq.imu.t_ns[0]) / 1e9
    fig, axes = plt.subplots(2, 1, figsize=(12, 6.5), sharex=True)
    for ax, data, unit, name in ((axes[0], seq.imu.gyro, "rad/s", "gyro"),
                                 (axes[1], seq.imu.accel, "m/s^2", "accel (specific force)")):
        for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.plot(t, data[:, k], lw=0.6, color=colour, label="xyz"[k])
        ax.set_ylabel(f"{name} [{unit}]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", ncol=3)
        motion_start = seq.meta.get("times_ns", {}).get("motion_start")
        if motion_start is not None:
            ax.axvspan(0, (motion_start - seq.imu.t_ns[0]) / 1e9, color="0.85", zorder=0)
    axes[1].set_xlabel("time [s] (shaded: held still)")
    fig.suptitle(f"{seq.name}: IMU in the body frame")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_allan(seq: Sequence, path: Path) -> Path:
    """Allan deviation of a static sequence (gravity and the constant biases do not matter)."""
    rate = 1e9 / np.median(np.diff(seq.imu.t_ns))
    n = seq.imu_noise
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, data, density, walk, unit, name in (
            (axes[0], seq.imu.gyro, n.gyroscope_noise_density, n.gyroscope_random_walk, "rad/s", "gyro"),
            (axes[1], seq.imu.accel, n.accelerometer_noise_density, n.accelerometer_random_walk, "m/s^2", "accel")):
        taus, adev = allan_deviation(data, rate)
        for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.loglog(taus, adev[:, k], color=colour, lw=1, label=f"{name} {'xyz'[k]}")
        ax.loglog(taus, expected_adev(taus, density, walk), "k--", lw=1.5,
                  label=f"expected: N={density:.3g}, K={walk:.3g}")
        ax.axvline(1.0, color="0.6", lw=0.8)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
    duration = (seq.imu.t_ns[-1] - seq.imu.t_ns[0]) / 1e9
    fig.suptitle(f"{seq.name}: Allan deviation of {duration:.0f} s static IMU (N read at tau = 1 s)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_sequence(root: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write the pictures of sequence `root` into out_dir (default: root/plots)."""
    seq = load(root)
    out = Path(out_dir) if out_dir is not None else Path(root) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    written = [plot_imu(seq, out / "imu.png")]
    if len(seq.gt_T_CO):
        written.insert(0, plot_trajectory(seq, out / "trajectory.png"))
    if seq.meta.get("generator", {}).get("motion") == "static":
        written.append(plot_allan(seq, out / "allan.png"))
    return written
