"""The filter's state: the nominal state (as the paper's tracker keeps it) plus an error covariance.

Nominal, as in `client_sdk.state`: `x` = (R_OB row-major 9, p_OB 3, v_OB 3) floats, `c` = (b_g 3,
b_a 3, g_O 3) floats, and the camera-IMU time offset `td` (s; t_imu = t_camera + td).

Error state (N = 19), in this order:

    d_theta 0:3   body-frame rotation error:      R_OB_true = R_OB Exp(d_theta)
    d_p     3:6   position error in O:            p_true = p + d_p
    d_v     6:9   velocity error in O
    d_bg    9:12  gyro bias error (body)
    d_ba   12:15  accelerometer bias error (body)
    d_g    15:18  gravity error in O: g_true = g + d_g (direction and norm: local gravity is 9.78-9.83
                  m/s^2, and a still start cannot tell it from the accelerometer bias, which a rotating
                  device then separates)
    d_td   18     time offset error, s
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client_sdk.propagation import rotate

N = 19
TH, P, V, BG, BA, G, TD = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15), slice(15, 18), 18


@dataclass
class FilterState:
    """The nominal state and covariance at one time (values are replaced, never mutated in place)."""

    x: tuple
    c: tuple
    cov: np.ndarray  # (N, N)
    phi: np.ndarray | None = None  # (N, N) the error transition from the last anchor, kept only while
    # the filter records its error dynamics (`eskf.error_dynamics`)
    held: tuple | None = None  # in a gap of the IMU's stream (`eskf.coasting`): (b_g, its 3x3 covariance, the
    # gap's start ns) kept aside while the slot of b_g holds minus the angular rate


def inject(x: tuple, c: tuple, td: float, dx: np.ndarray, gravity_state: bool = True) -> tuple[tuple, tuple, float]:
    """The nominal state corrected by an error-state estimate dx (the ESKF's injection)."""
    d = dx.tolist()
    R = rotate(x, d[0], d[1], d[2])
    xn = R + (x[9] + d[3], x[10] + d[4], x[11] + d[5], x[12] + d[6], x[13] + d[7], x[14] + d[8])
    g = tuple(c[6 + k] + d[15 + k] for k in range(3)) if gravity_state else c[6:9]
    cn = tuple(c[k] + d[9 + k] for k in range(6)) + g
    return xn, cn, td + d[18]
