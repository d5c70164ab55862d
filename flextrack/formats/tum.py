"""TUM trajectory files (`timestamp tx ty tz qx qy qz qw`, seconds), readable by evo."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flextrack.geometry import se3


def write_tum(path: str | Path, t_ns: np.ndarray, poses: np.ndarray) -> None:
    """Write (N,) ns times and (N, 4, 4) poses. Note TUM's quaternion order: x y z w."""
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(t_ns, poses):
            q, p = se3.to_quat_translation(T)
            f.write(f"{int(t) // 1_000_000_000}.{int(t) % 1_000_000_000:09d} "
                    f"{p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}\n")

