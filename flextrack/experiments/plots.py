"""The experiments' PNG figures."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from flextrack.experiments import paper


def table2(rows: list[list], path: Path) -> Path:
    """2D error against frame rate, one line per program, ours (solid) and the paper's (dashed)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, backend in zip(axes, paper.BACKENDS):
        for k, (motion, level) in enumerate([(m, lv) for m in paper.MOTIONS for lv in paper.LEVELS]):
            pts = [(r[2], r[7]) for r in rows if r[0] == motion and r[1] == level and r[3] == backend]
            if not pts:
                continue
            fps = sorted({p[0] for p in pts})
            ours = [np.mean([p[1] for p in pts if p[0] == f]) for f in fps]
            c = colours[k % len(colours)]
            ax.plot(fps, ours, "-o", color=c, ms=4, label=f"{motion} {level}")
            ax.plot(fps, [paper.TABLE2[(motion, level, int(f), backend)][2] for f in fps], "--", color=c, lw=1)
        ax.set_title(f"{'GT' if backend == 'gt' else 'Noisy'} backend (solid: ours, dashed: paper)")
        ax.set_xlabel("frame rate [FPS]")
        ax.set_ylabel("mean 2D projection error [px]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ablation(rows: list[list], path: Path) -> Path:
    """Mean 2D error per variant and backend (log scale: IMU only is orders of magnitude off)."""
    variants = list(dict.fromkeys(r[0] for r in rows))
    fig, ax = plt.subplots(figsize=(8, 4.2))
    width = 0.38
    for k, backend in enumerate(paper.BACKENDS):
        means = [np.mean([r[5] for r in rows if r[0] == v and r[1] == backend]) for v in variants]
        bars = ax.bar(np.arange(len(variants)) + (k - 0.5) * width, means, width, label=backend)
        ax.bar_label(bars, fmt="%.2f", fontsize=8)
    ax.set_xticks(np.arange(len(variants)), variants)
    ax.set_yscale("log")
    ax.set_ylabel("mean 2D projection error [px]")
    ax.set_title("ablation (mean over programs)")
    ax.legend()
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _error_series(series: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str, *,
                  markers: bool, log: bool) -> Path:
    fig, ax = plt.subplots(figsize=(9, 3.8))
    for name, (t_s, px) in series.items():
        ax.plot(t_s, px, "-o" if markers else "-", ms=2.5, lw=0.8, label=name)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("2D projection error [px]")
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def sawtooth(series: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str) -> Path:
    """Per-frame 2D error over about one second (the paper's Figure 5), one marker a frame."""
    return _error_series(series, path, title, markers=True, log=False)


def error_over_time(series: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str) -> Path:
    """2D error over a whole run, log scale (errors span 0.1 to 1000 px across variants)."""
    return _error_series(series, path, title, markers=False, log=True)
