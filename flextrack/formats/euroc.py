"""EuRoC ASL csv files: IMU samples and the state_groundtruth_estimate0 table."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

IMU_HEADER = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


@dataclass
class ImuData:
    t_ns: np.ndarray  # (N,) int64
    gyro: np.ndarray  # (N, 3) rad/s, body frame
    accel: np.ndarray  # (N, 3) m/s^2 specific force, body frame


@dataclass
class GroundTruth:
    """Body (IMU) state in the world at the IMU rate; quaternion q_WB in w, x, y, z order."""

    t_ns: np.ndarray  # (N,) int64
    p_WB: np.ndarray  # (N, 3)
    q_WB: np.ndarray  # (N, 4) w x y z
    v_WB: np.ndarray  # (N, 3)
    bias_gyro: np.ndarray  # (N, 3)
    bias_accel: np.ndarray  # (N, 3)


def _read_table(path: Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer first column (ns) and float rest; exact int64 timestamps, never through float."""
    times, values = [], []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split(",")
            if len(parts) < columns:
                raise ValueError(f"{path}:{line_no}: expected {columns} columns, got {len(parts)}")
            times.append(int(parts[0]))
            values.append([float(p) for p in parts[1:columns]])
    return np.asarray(times, dtype=np.int64), np.asarray(values, dtype=float).reshape(-1, columns - 1)


def read_imu(path: str | Path) -> ImuData:
    t, v = _read_table(Path(path), 7)
    return ImuData(t, v[:, 0:3], v[:, 3:6])


def write_imu(path: str | Path, imu: ImuData) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        f.write(IMU_HEADER + "\n")
        f.writelines(f"{int(t)}," + ",".join(f"{x:.10g}" for x in (*g, *a)) + "\n" for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel))


def read_groundtruth(path: str | Path) -> GroundTruth:
    t, v = _read_table(Path(path), 17)
    return GroundTruth(t, v[:, 0:3], v[:, 3:7], v[:, 7:10], v[:, 10:13], v[:, 13:16])


def write_groundtruth(path: str | Path, gt: GroundTruth) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    rows = np.hstack([gt.p_WB, gt.q_WB, gt.v_WB, gt.bias_gyro, gt.bias_accel])
    with open(path, "w") as f:
        f.write(GT_HEADER + "\n")
        f.writelines(f"{int(t)}," + ",".join(f"{x:.10g}" for x in r) + "\n" for t, r in zip(gt.t_ns, rows))
