"""The filter's first state: the first backend pose, gravity and gyro bias from the IMU window before it.

A still window measures gravity in the body frame (minus the mean accelerometer) and the gyro bias
(the mean gyro) to the standard errors of those means (for 0.5 s of a simulated Pixel 2 at 200 Hz,
~0.001 m/s^2 and ~0.1 mrad/s), never better than `still_gravity_std` and `still_gyro_bias_std`. A
moving one still gives gravity's direction: carried back from the pose by the gyro, the specific
forces average to -g_O over a window in which the device's own acceleration averages out (hand
motion: ~0.1-0.3 m/s^2 over half a second), so the filter starts from that with an honest
uncertainty (`init_gravity_std`, its norm standard gravity's) and the answers that follow refine it.
Velocity starts at zero with `init_velocity_std` (near zero when still).
"""

from __future__ import annotations

import numpy as np

from client_sdk import initialization
from client_sdk.eskf.options import FilterOptions
from client_sdk.eskf.pose_update import offset_terms, pose_jacobian, skew
from client_sdk.eskf.state import BA, BG, TD, TH, FilterState, G, N, V
from client_sdk.propagation import NS, rotate

STANDARD_GRAVITY = 9.80665


def _gravity_from_motion(R_OB: tuple, window: list[tuple], b_g: tuple) -> np.ndarray:
    """-mean(R_OB(t_i) f_i) with R_OB(t_i) carried back from the pose at the window's end by the gyro."""
    R = R_OB
    acc = np.zeros(3)
    for k in range(len(window) - 1, -1, -1):
        s = window[k]
        Rm = np.array(R).reshape(3, 3)
        acc += Rm @ np.array(s[4:7])
        if k:
            dt = (s[0] - window[k - 1][0]) * NS
            R = rotate(R, -(s[1] - b_g[0]) * dt, -(s[2] - b_g[1]) * dt, -(s[3] - b_g[2]) * dt)
    g = -acc / len(window)
    return g / np.linalg.norm(g) * STANDARD_GRAVITY


def initial_state(x_pose: tuple, T_CO_sigma: np.ndarray, window: list[tuple], R_CB: np.ndarray,
                  est: initialization.InitEstimate, options: FilterOptions, gyro: tuple = (0.0, 0.0, 0.0),
                  gyro_var: float = 0.0, td_std: float | None = None) -> FilterState:
    """The state at the first answer's time: pose from it (x_pose: R_OB 9, p_OB 3), the rest from the window.
    `gyro`: the raw gyro rate at that time, `gyro_var` its sample noise's variance per axis; `td_std` the
    time offset's uncertainty (default `time_offset_std_s`; a re-initialisation keeps what it had learnt).

    The answer shows the pose at its time plus the unknown time offset error d_td: on a moving device
    the first pose's error is -H_pose^-1 (H_td d_td + n), so it starts correlated with d_td (and takes
    the second-order products of d_td with the rates' errors, as an update does, `offset_terms`)."""
    R_OB = x_pose[0:9]
    if est.still:
        b_g = tuple(est.b_g.tolist())
        g_O = np.array(R_OB).reshape(3, 3) @ est.g_B
        # the window's means are known to their standard errors (samples counted as independent only as far
        # as their autocorrelation allows: tremor, vibration); the floors stand for slow motion none shows
        g_std = max(est.accel_mean_std, options.still_gravity_std)
        bg_std = max(est.gyro_mean_std, options.still_gyro_bias_std)
        v_std = 0.02
    else:
        b_g = (0.0, 0.0, 0.0)
        g_O = _gravity_from_motion(R_OB, window, b_g)
        g_std, v_std, bg_std = options.init_gravity_std, options.init_velocity_std, options.init_gyro_bias_std
    x = tuple(x_pose[0:12]) + (0.0, 0.0, 0.0)
    c = b_g + (0.0, 0.0, 0.0) + tuple(g_O.tolist())
    cov = np.zeros((N, N))
    cov[V, V] = np.eye(3) * v_std ** 2
    cov[BG, BG] = np.eye(3) * bg_std ** 2
    cov[BA, BA] = np.eye(3) * options.init_accel_bias_std ** 2
    td_var = (options.time_offset_std_s if td_std is None else td_std) ** 2
    cov[TD, TD] = td_var
    # the pose block: the answer's covariance mapped back through the measurement Jacobian, with the
    # time offset's share (the velocity is estimated 0: its part of H_td is second order)
    w = tuple(gyro[i] - b_g[i] for i in range(3))
    _, _, H = pose_jacobian(x, R_CB, w, (0.0, 0.0, 0.0))
    H_inv = np.linalg.inv(H[:, 0:6])
    extra, _ = offset_terms(H, cov, gyro_var)
    k = -np.dot(H_inv, H[:, TD])
    cov[0:6, 0:6] = H_inv @ (T_CO_sigma + extra) @ H_inv.T + np.outer(k, k) * td_var
    cov[0:6, TD] = cov[TD, 0:6] = k * td_var
    if options.gravity_state:
        # g_O = R_OB (b_a - f_mean) moves with the first pose's orientation error and with the accelerometer
        # bias the window could not tell from gravity: d_g = J_th d_theta + J_ba d_ba + noise
        R = np.array(R_OB).reshape(3, 3)
        J = np.zeros((3, N))
        J[:, TH] = -R @ skew(R.T @ g_O)
        J[:, BA] = R
        cross, gg = J @ cov, J @ cov @ J.T + np.eye(3) * g_std ** 2
        cov[G, :], cov[:, G] = cross, cross.T
        cov[G, G] = gg
    return FilterState(x, c, 0.5 * (cov + cov.T))
