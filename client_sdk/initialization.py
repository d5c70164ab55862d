"""The paper's "System Initialization": gravity and gyro bias from the IMU while the device is still.

Over a window of `init_window_s` ending at the first backend frame, a still device measures
f_B = -g_B + b_a and w_B = b_g (+ noise). So the mean gyro is the gyro bias and minus the mean
accelerometer is gravity in the body frame (the accelerometer bias cannot be told apart from gravity
here; it is left at zero and BSCM takes it up later). The first backend pose R_OB then gives
g_O = R_OB g_B; the velocity starts at zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from client_sdk.imu_buffer import ImuBuffer
from client_sdk.options import TrackerOptions
from flextrack.autocorrelation import standard_error_of_mean


@dataclass(frozen=True)
class InitEstimate:
    g_B: np.ndarray  # gravity in the body frame, m/s^2 (points down)
    b_g: np.ndarray  # gyro bias, rad/s
    gyro_std: float  # RMS deviation from the mean over the window, rad/s
    accel_std: float  # m/s^2
    still: bool
    window: np.ndarray = field(repr=False)  # (N, 6) gyro, accel samples the means are of

    @property
    def gyro_mean_std(self) -> float:
        """Standard error of the mean gyro (the bias), per axis, rad/s; computed when asked (the filter's
        still start), not on every initialising frame."""
        return standard_error_of_mean(self.window[:, 0:3])

    @property
    def accel_mean_std(self) -> float:
        """The same of the mean specific force, m/s^2."""
        return standard_error_of_mean(self.window[:, 3:6])


def estimate(samples: list[tuple], options: TrackerOptions) -> InitEstimate:
    """Gravity, gyro bias and stillness from IMU samples `(t_ns, w 3, a 3)`."""
    a = np.array(samples, dtype=float)[:, 1:]
    mean = a.mean(axis=0)
    gyro_std = float(np.sqrt(((a[:, 0:3] - mean[0:3]) ** 2).sum(axis=1).mean()))
    accel_std = float(np.sqrt(((a[:, 3:6] - mean[3:6]) ** 2).sum(axis=1).mean()))
    still = gyro_std < options.still_gyro_std and accel_std < options.still_accel_std
    return InitEstimate(-mean[3:6], mean[0:3], gyro_std, accel_std, still, a)


def assess(buffer: ImuBuffer, t_ns: int, options: TrackerOptions) -> tuple[InitEstimate | None, str]:
    """The estimate for a first backend frame at t_ns, or None and the reason it cannot be used yet."""
    window_ns = round(options.init_window_s * 1e9)
    if not len(buffer):
        return None, "initializing: waiting for IMU samples"
    have_s = (min(t_ns, buffer.last_t_ns) - buffer.first_t_ns) * 1e-9
    samples = buffer.window(t_ns - window_ns, t_ns)
    if buffer.first_t_ns > t_ns - window_ns or len(samples) < 2:
        return None, f"initializing: collecting IMU ({max(have_s, 0.0):.2f} of {options.init_window_s:.2f} s)"
    est = estimate(samples, options)
    if options.init_require_still and not est.still:
        return None, (f"initializing: hold the device still (gyro {est.gyro_std:.3f} rad/s, "
                      f"accel {est.accel_std:.3f} m/s^2 RMS; limits {options.still_gyro_std}, "
                      f"{options.still_accel_std})")
    return est, "initializing: waiting for the first backend pose"
