"""A fourth-order strapdown integrator: the checking tool that proves the IMU matches the trajectory.

Per step [t_k, t_k+1] of length h:
- rotation: fourth-order Magnus expansion with the gyro at the two Gauss points,
  Omega = h/2 (w1 + w2) + sqrt(3)/12 h^2 (w1 x w2), and the same on the half step for the midpoint
  attitude; attitudes are the running product of the step rotations (a vectorised prefix product);
- velocity: Simpson's rule on a_W = R f + g at t_k, the midpoint and t_k+1;
- position: p_k+1 = p_k + h v_k + h^2/6 (a_k + 2 a_mid), exact for a quadratic a_W.
The IMU at the intermediate times comes from `imu_at(t) -> (gyro, accel)` when the exact signal is
known, else from a cubic spline through the samples (what any propagation of samples can do).
Biases, when given per sample, are removed first. The tracker has its own propagation; this one
only checks the simulator (and the EuRoC conversion).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from flextrack.geometry import so3
from flextrack.simulator.kinematics import GRAVITY_W

_GAUSS = 0.5 - np.sqrt(3) / 6, 0.5 + np.sqrt(3) / 6


@dataclass
class Integrated:
    R_WB: np.ndarray  # (N, 3, 3) at the sample times
    p_WB: np.ndarray  # (N, 3)
    v_WB: np.ndarray  # (N, 3)


def _magnus(w1: np.ndarray, w2: np.ndarray, h: np.ndarray) -> np.ndarray:
    return so3.exp_many(0.5 * h[:, None] * (w1 + w2) + (np.sqrt(3) / 12) * h[:, None] ** 2 * np.cross(w1, w2))


def _prefix_product(R0: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """[R0, R0 S0, R0 S0 S1, ...] by doubling (log2 N batched products)."""
    out = np.concatenate([R0[None], steps], axis=0)
    shift = 1
    while shift < len(out):
        out[shift:] = out[:-shift] @ out[shift:]
        shift *= 2
    return out


def integrate(t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, R0: np.ndarray, p0: np.ndarray,
              v0: np.ndarray, *, imu_at: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
              bias_gyro: np.ndarray | None = None, bias_accel: np.ndarray | None = None,
              gravity_W: np.ndarray = GRAVITY_W) -> Integrated:
    """Body pose and velocity at every sample time, from the state at the first sample."""
    t = np.asarray(t_s, float)
    gyro = np.asarray(gyro, float) - (0.0 if bias_gyro is None else bias_gyro)
    accel = np.asarray(accel, float) - (0.0 if bias_accel is None else bias_accel)
    h = np.diff(t)
    if imu_at is None:
        gyro_spline, accel_spline = CubicSpline(t, gyro, axis=0), CubicSpline(t, accel, axis=0)
        imu_at = lambda tq: (gyro_spline(tq), accel_spline(tq))
    t0 = t[:-1]
    w_g1, _ = imu_at(t0 + _GAUSS[0] * h)
    w_g2, _ = imu_at(t0 + _GAUSS[1] * h)
    w_h1, _ = imu_at(t0 + _GAUSS[0] * h / 2)
    w_h2, _ = imu_at(t0 + _GAUSS[1] * h / 2)
    _, f_mid = imu_at(t0 + h / 2)
    R = _prefix_product(np.asarray(R0, float), _magnus(w_g1, w_g2, h))
    R_mid = R[:-1] @ _magnus(w_h1, w_h2, h / 2)
    a = np.einsum("nij,nj->ni", R, accel) + gravity_W
    a_mid = np.einsum("nij,nj->ni", R_mid, f_mid) + gravity_W
    dv = h[:, None] / 6 * (a[:-1] + 4 * a_mid + a[1:])
    v = np.vstack([v0, v0 + np.cumsum(dv, axis=0)])
    dp = h[:, None] * v[:-1] + h[:, None] ** 2 / 6 * (a[:-1] + 2 * a_mid)
    p = np.vstack([p0, p0 + np.cumsum(dp, axis=0)])
    return Integrated(R, p, v)
