"""The tracker's state vector and its wire form.

Frames: O object, B IMU body. The state at time `t_ns` is the IMU body's orientation `R_OB`,
position `p_OB` and velocity `v_OB` in the object frame, the gyro bias `b_g` and accelerometer bias
`b_a` in the body frame, and gravity `g_O` in the object frame.

Gravity sign convention: `g_O` is the gravitational acceleration itself (it points down, |g_O| ~ 9.81).
The accelerometer measures the specific force f_B = R_OB^T (a_O - g_O) + b_a, so the acceleration
used by propagation is a_O = R_OB (f_B - b_a) + g_O. The paper writes R a - g with g pointing up;
the two agree with g_paper = -g_O.

Inside the hot loops the kinematic part travels as a flat tuple of 15 floats
`(R_OB row-major 9, p_OB 3, v_OB 3)` ("nominal tuple") and the constant part as a tuple of 9 floats
`(b_g 3, b_a 3, g_O 3)` ("constants"): plain floats are faster than numpy for 3x3 arithmetic.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

MAGIC = b"FTS1"
_HEADER = struct.Struct("<4sqI")  # magic, t_ns, number of IMU rows
STATE_FLOATS = 24  # R 9, p 3, v 3, b_g 3, b_a 3, g 3
IMU_ROW = 7  # t_s relative to the state time, gyro 3, accel 3


@dataclass
class TrackerState:
    """The nominal state at t_ns: the body's pose in the object frame (R_OB, p_OB, m), its velocity
    (m/s), the gyro and accelerometer biases (rad/s, m/s^2) and gravity in the object frame (m/s^2)."""

    t_ns: int
    R_OB: np.ndarray
    p_OB: np.ndarray
    v_OB: np.ndarray
    b_g: np.ndarray
    b_a: np.ndarray
    g_O: np.ndarray

    @classmethod
    def from_tuples(cls, t_ns: int, x: tuple, c: tuple) -> TrackerState:
        """Build from a nominal tuple and a constants tuple (see module doc)."""
        return cls(
            int(t_ns),
            np.array(x[0:9], dtype=float).reshape(3, 3),
            np.array(x[9:12], dtype=float),
            np.array(x[12:15], dtype=float),
            np.array(c[0:3], dtype=float),
            np.array(c[3:6], dtype=float),
            np.array(c[6:9], dtype=float),
        )

    def as_vector(self) -> np.ndarray:
        """The 24 floats R_OB (row-major), p_OB, v_OB, b_g, b_a, g_O."""
        return np.concatenate([self.R_OB.ravel(), self.p_OB, self.v_OB, self.b_g, self.b_a, self.g_O])

    def T_OB(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R_OB
        T[:3, 3] = self.p_OB
        return T


def encode(state: TrackerState, imu_rows: np.ndarray) -> bytes:
    """The state and recent IMU rows `(N, 7)`: t_s relative to `state.t_ns`, gyro, accel; float64 LE."""
    imu_rows = np.ascontiguousarray(imu_rows, dtype="<f8").reshape(-1, IMU_ROW)
    return (
        _HEADER.pack(MAGIC, int(state.t_ns), len(imu_rows))
        + state.as_vector().astype("<f8").tobytes()
        + imu_rows.tobytes()
    )


def decode(blob: bytes) -> tuple[TrackerState, np.ndarray]:
    """Inverse of `encode`; ValueError on anything that is not such a blob."""
    if len(blob) < _HEADER.size + 8 * STATE_FLOATS:
        raise ValueError("tracker state blob too short")
    magic, t_ns, rows = _HEADER.unpack_from(blob)
    if magic != MAGIC:
        raise ValueError(f"not a tracker state blob (magic {magic!r})")
    expected = _HEADER.size + 8 * (STATE_FLOATS + IMU_ROW * rows)
    if len(blob) != expected:
        raise ValueError(f"tracker state blob has {len(blob)} bytes, expected {expected}")
    v = np.frombuffer(blob, dtype="<f8", count=STATE_FLOATS, offset=_HEADER.size).astype(float)
    imu = np.frombuffer(blob, dtype="<f8", offset=_HEADER.size + 8 * STATE_FLOATS).astype(float)
    state = TrackerState(t_ns, v[0:9].reshape(3, 3), v[9:12], v[12:15], v[15:18], v[18:21], v[21:24])
    return state, imu.reshape(rows, IMU_ROW)


def blob(st: TrackerState | None, now_ns: int | None, buffer, n_samples: int) -> bytes:
    """`encode` of a tracker's state (identity / zeros at `now_ns` before initialisation) and the newest
    `n_samples` samples of its `ImuBuffer`, their times relative to the state's."""
    if st is None:
        z = np.zeros(3)
        st = TrackerState(now_ns or 0, np.eye(3), z, z, z, z, z)
    times, samples = buffer.recent(n_samples)
    rows = np.array(samples, dtype=float).reshape(-1, 7)
    rows[:, 0] = (np.array(times, dtype=np.int64) - st.t_ns) * 1e-9  # exact in integers first
    return encode(st, rows)
