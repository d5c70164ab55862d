"""The filter's state: the nominal state (as the paper's tracker keeps it) plus an error covariance.

Nominal, as in `client_sdk.state`: `x` = (R_OB row-major 9, p_OB 3, v_OB 3) floats, `c` = (b_g 3,
b_a 3, g_O 3) floats, and the camera-IMU time offset `td` (s; t_imu = t_camera + td).

Error state (N = 18), in this order:

    d_theta 0:3   body-frame rotation error:      R_OB_true = R_OB Exp(d_theta)
    d_p     3:6   position error in O:            p_true = p + d_p
    d_v     6:9   velocity error in O
    d_bg    9:12  gyro bias error (body)
    d_ba   12:15  accelerometer bias error (body)
    d_g    15:17  gravity direction error, on the tangent plane of g_O: g_true = |g| normalise(g + B d_g)
    d_td   17     time offset error, s

`B` (3x2) is an orthonormal basis of the plane normal to g_O; the gravity's norm is not a state.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import sqrt

import numpy as np

from client_sdk.propagation import rotate

N = 18
TH, P, V, BG, BA, G, TD = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15), slice(15, 17), 17


@dataclass
class FilterState:
    """The nominal state and covariance at one time (values are replaced, never mutated in place)."""

    x: tuple
    c: tuple
    cov: np.ndarray  # (N, N)


def gravity_basis(g: tuple) -> tuple:
    """Two unit vectors (6 floats, b1 then b2) spanning the plane normal to g."""
    n = sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    ux, uy, uz = g[0] / n, g[1] / n, g[2] / n
    # the world axis least aligned with g, made orthogonal to it
    if abs(ux) <= abs(uy) and abs(ux) <= abs(uz):
        a = (1.0, 0.0, 0.0)
    elif abs(uy) <= abs(uz):
        a = (0.0, 1.0, 0.0)
    else:
        a = (0.0, 0.0, 1.0)
    d = a[0] * ux + a[1] * uy + a[2] * uz
    b1 = (a[0] - d * ux, a[1] - d * uy, a[2] - d * uz)
    m = sqrt(b1[0] ** 2 + b1[1] ** 2 + b1[2] ** 2)
    b1 = (b1[0] / m, b1[1] / m, b1[2] / m)
    b2 = (uy * b1[2] - uz * b1[1], uz * b1[0] - ux * b1[2], ux * b1[1] - uy * b1[0])
    return b1 + b2


def inject(x: tuple, c: tuple, td: float, dx: np.ndarray, gravity_state: bool = True) -> tuple[tuple, tuple, float]:
    """The nominal state corrected by an error-state estimate dx (the ESKF's injection)."""
    d = dx.tolist()
    R = rotate(x, d[0], d[1], d[2])
    xn = R + (x[9] + d[3], x[10] + d[4], x[11] + d[5], x[12] + d[6], x[13] + d[7], x[14] + d[8])
    g = c[6:9]
    if gravity_state:
        b = gravity_basis(g)
        norm = sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2)
        gn = tuple(g[k] + b[k] * d[15] + b[3 + k] * d[16] for k in range(3))
        s = norm / sqrt(gn[0] ** 2 + gn[1] ** 2 + gn[2] ** 2)
        g = tuple(e * s for e in gn)
    cn = tuple(c[k] + d[9 + k] for k in range(6)) + tuple(g)
    return xn, cn, td + d[17]
