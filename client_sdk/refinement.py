"""PRM bookkeeping (which backend request is in flight) and BSCM, the Bias Self-Correction Mechanism.

BSCM (the paper's Section 3.4) runs when a backend pose arrives for capture time t1 and the previous
backend pose was at t0 (here `t_ref`, with nothing in between having reset the PRM). The paper is
loose in three places; what is done here instead:

1. Gyro bias. The paper takes R_bias = R_imu R_real^-1, decomposes it into XYZ Euler angles and
   divides by the elapsed time. R_imu R_real^-1 is the drift expressed in the *object* frame (a left
   perturbation), but the gyro bias lives in the *body* frame, and Euler angles are not a rotation
   rate. Propagation with a bias error db gives R_imu = R_real Exp(db dt) (a right perturbation,
   exact for constant body rates, first order otherwise), so here the drift is
   d_theta_B = Log(R_real^T R_imu), a rotation vector in the body frame, and b_g += d_theta_B / dt.
2. Velocity. V_avg = (T_t1 - T_t0) / (t1 - t0) is the average velocity over the interval, i.e. the
   velocity at the mid-time (exact for constant acceleration). V_bias = V_imu(mid) - V_avg, with
   V_imu(mid) interpolated from the per-sample states. The paper does not say which velocity the
   state gets at t1; here v(t1) = V_imu(t1) - V_bias (V_avg carried to t1 by the IMU's velocity
   change from the mid-time), scaled by `velocity_gain`. The positions the caller passes need not be
   the backend's own p_OB: by default the tracker passes the backend's camera-frame translation put
   into O with the propagated orientation (`TrackerOptions.bscm_imu_orientation`), which removes the
   backend's orientation noise times the object distance from V_avg.
3. Accelerometer bias. The paper's a_bias = V_bias / (t1 - t0) is an acceleration in the object
   frame; the bias lives in the body frame, so it is rotated by R_OB(mid)^T before it is added (a
   velocity that is too high means a_O = R (f - b_a) + g_O was too high, so b_a grows). For a
   constant bias error with an exact starting velocity V_bias is half the velocity drift, so the
   paper's formula removes about half of the error per correction; repeated corrections converge.

Gains below 1 and norm clamps (`TrackerOptions`) keep the estimates stable with a noisy backend.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from math import acos, sin, sqrt

import numpy as np

from client_sdk.propagation import rotate
from flextrack.geometry import so3


@dataclass(frozen=True)
class RefinementRequest:
    """Tells the shell: send the frame captured at `frame_t_ns` to the backend under `request_id`."""

    frame_t_ns: int
    request_id: int
    reason: str  # "init" (first pose), "refine" (the PRM's regular request), "failure" (sent by the PIM)


class ResponseOutcome(enum.Enum):
    """What `on_backend_response` did with a backend answer (the comments say when each happens)."""

    INITIALIZED = "initialized"  # the first backend pose started tracking
    APPLIED = "applied"  # state reset at the capture time, BSCM run, IMU re-propagated
    REJECTED = "rejected"  # the backend found no pose (ok=False); a new request goes out
    GATED = "gated"  # the pose disagrees with the tracked one beyond `backend_gate_px`: ignored, asked again
    STALE = "stale"  # not the request in flight (abandoned by a PRM reset, or unknown): ignored
    TOO_OLD = "too_old"  # the capture time is older than the IMU buffer: dropped


class RequestBook:
    """At most one live backend request; ids increase from 1."""

    def __init__(self) -> None:
        self._next_id = 1
        self.in_flight: RefinementRequest | None = None

    def issue(self, frame_t_ns: int, reason: str) -> RefinementRequest:
        self.in_flight = RefinementRequest(int(frame_t_ns), self._next_id, reason)
        self._next_id += 1
        return self.in_flight

    def is_live(self, request_id: int) -> bool:
        return self.in_flight is not None and self.in_flight.request_id == request_id


def log_rotation(R: tuple) -> tuple[float, float, float]:
    """Rotation vector of a row-major 9-tuple rotation (fast path; so3.log near pi)."""
    c = 0.5 * (R[0] + R[4] + R[8] - 1.0)
    c = min(max(c, -1.0), 1.0)
    angle = acos(c)
    if angle > 3.1:
        return tuple(so3.log(np.array(R).reshape(3, 3)))
    k = 0.5 + angle * angle / 12.0 if angle < 1e-4 else 0.5 * angle / sin(angle)
    return k * (R[7] - R[5]), k * (R[2] - R[6]), k * (R[3] - R[1])


def _clamp(v: tuple, limit: float) -> tuple:
    n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if n <= limit or n == 0.0:
        return v
    s = limit / n
    return v[0] * s, v[1] * s, v[2] * s


def _mat_t_mat(A: tuple, B: tuple) -> tuple:
    """A^T B for row-major 9-tuples."""
    return tuple(A[k] * B[m] + A[3 + k] * B[3 + m] + A[6 + k] * B[6 + m] for k in range(3) for m in range(3))


@dataclass(frozen=True)
class BscmResult:
    c: tuple  # new constants (b_g, b_a, g_O)
    v: tuple  # velocity at the capture time
    d_theta_B: tuple  # rotation drift since the last backend pose, body frame, rad
    v_bias: tuple  # V_imu(mid) - V_avg, object frame, m/s
    accepted: bool  # False: an outlier, c and v left as they were


def bscm(c: tuple, x_imu: tuple, R_real: tuple, p_real: tuple, p_ref: tuple, x_mid: tuple, dt: float,
         gyro_gain: float, accel_gain: float, velocity_gain: float, max_gyro_bias: float,
         max_accel_bias: float, max_velocity_error: float, max_rotation_rate: float,
         dt_rot: float | None = None) -> BscmResult:
    """One BSCM correction (see module doc). `x_imu`: propagated state at the capture time t1;
    `R_real`, `p_real`: the backend's R_OB, p_OB at t1; `p_ref`: the backend p_OB at t0;
    `x_mid`: propagated state at (t0 + t1) / 2; `dt` = t1 - t0 in s; `dt_rot`: the time since the
    orientation was last set from a backend pose (the span of the rotation drift; default dt).
    Outliers beyond `max_velocity_error` (m/s) or `max_rotation_rate` (rad/s) change nothing
    (accepted=False)."""
    dt_rot = dt if dt_rot is None or dt_rot <= 0 else dt_rot
    d = log_rotation(_mat_t_mat(R_real, x_imu[0:9]))
    v_bias = tuple(x_mid[12 + k] - (p_real[k] - p_ref[k]) / dt for k in range(3))
    if sqrt(sum(e * e for e in v_bias)) > max_velocity_error or \
            sqrt(sum(e * e for e in d)) > max_rotation_rate * dt_rot:
        return BscmResult(c, x_imu[12:15], d, v_bias, False)
    b_g = _clamp(tuple(c[k] + gyro_gain * d[k] / dt_rot for k in range(3)), max_gyro_bias)
    v = tuple(x_imu[12 + k] - velocity_gain * v_bias[k] for k in range(3))
    da = tuple(accel_gain * v_bias[k] / dt for k in range(3))
    Rm = x_mid[0:9]  # b_a += R_OB(mid)^T da
    b_a = _clamp(tuple(c[3 + k] + Rm[k] * da[0] + Rm[3 + k] * da[1] + Rm[6 + k] * da[2] for k in range(3)),
                 max_accel_bias)
    return BscmResult(b_g + b_a + tuple(c[6:9]), v, d, v_bias, True)


def blend_pose(x_imu: tuple, R_real: tuple, p_real: tuple, gain: float) -> tuple[tuple, tuple]:
    """(R, p) a fraction `gain` of the way from the propagated pose to the backend's, rotation along
    the geodesic (body frame), position linearly; gain 1 returns the backend pose itself."""
    if gain >= 1.0:
        return R_real, p_real
    d = log_rotation(_mat_t_mat(x_imu[0:9], R_real))
    R = rotate(x_imu, gain * d[0], gain * d[1], gain * d[2])
    return R, tuple(x_imu[9 + k] + gain * (p_real[k] - x_imu[9 + k]) for k in range(3))
