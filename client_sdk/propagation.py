"""PPM: propagate the nominal state over one IMU interval (the paper's Section 3.3).

Two integrators with one signature `step(x, c, t0_ns, t1_ns, s0, s1) -> x`: `x` the nominal tuple
at t0 (see `client_sdk.state`), `c` the constants `(b_g, b_a, g_O)`, `s0` / `s1` the raw IMU samples
`(t_ns, w 3, a 3)` at or before t0 and after it (the same sample when extrapolating past the newest).

- `step_paper`, the paper's Eqs. 2-7: the rate at the end of the interval for the whole interval,
  R <- R Exp((w - b_g) dt) (Rodrigues), then v <- v + dt (R (a - b_a) + g_O) with the *new* R, then
  p <- p + dt v with the *new* v (semi-implicit Euler, first order).
- `step_midpoint`: rates linearly interpolated to both ends of the interval, the rotation with the
  mean rate, the acceleration averaged over both ends (trapezoid), p with the exact constant-
  acceleration term (second order). docs/tracker.md compares the two.

The 3x3 algebra is written out on Python floats on purpose: for 3-vectors this is several times
faster than numpy calls (each costs ~1 us), and this runs for every IMU sample and every
re-propagated one. `flextrack.geometry.so3.exp` is the reference it is tested against.
"""

from __future__ import annotations

from math import cos, sin, sqrt

NS = 1e-9
_TAYLOR_TH2 = 1e-8  # below this squared angle, the Rodrigues coefficients by their Taylor series


def rotate(x: tuple, wx: float, wy: float, wz: float) -> tuple:
    """R E as 9 floats, R = x[0:9] row-major and E = Exp([wx, wy, wz]) (Rodrigues, the paper's Eq. 2)."""
    th2 = wx * wx + wy * wy + wz * wz
    if th2 < _TAYLOR_TH2:
        A = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        B = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = sqrt(th2)
        A = sin(th) / th
        B = (1.0 - cos(th)) / th2
    # E = I + A [w]x + B [w]x^2, with [w]x^2 = w w^T - th2 I
    bxy, bxz, byz = B * wx * wy, B * wx * wz, B * wy * wz
    e00, e11, e22 = 1.0 - B * (wy * wy + wz * wz), 1.0 - B * (wx * wx + wz * wz), 1.0 - B * (wx * wx + wy * wy)
    e01, e10 = bxy - A * wz, bxy + A * wz
    e02, e20 = bxz + A * wy, bxz - A * wy
    e12, e21 = byz - A * wx, byz + A * wx
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = x[0:9]
    return (
        r00 * e00 + r01 * e10 + r02 * e20, r00 * e01 + r01 * e11 + r02 * e21, r00 * e02 + r01 * e12 + r02 * e22,
        r10 * e00 + r11 * e10 + r12 * e20, r10 * e01 + r11 * e11 + r12 * e21, r10 * e02 + r11 * e12 + r12 * e22,
        r20 * e00 + r21 * e10 + r22 * e20, r20 * e01 + r21 * e11 + r22 * e21, r20 * e02 + r21 * e12 + r22 * e22,
    )


def step_paper(x: tuple, c: tuple, t0_ns: int, t1_ns: int, s0: tuple, s1: tuple) -> tuple:
    dt = (t1_ns - t0_ns) * NS
    _, gx, gy, gz, ax, ay, az = s1
    R = rotate(x, (gx - c[0]) * dt, (gy - c[1]) * dt, (gz - c[2]) * dt)
    fx, fy, fz = ax - c[3], ay - c[4], az - c[5]
    vx = x[12] + dt * (R[0] * fx + R[1] * fy + R[2] * fz + c[6])
    vy = x[13] + dt * (R[3] * fx + R[4] * fy + R[5] * fz + c[7])
    vz = x[14] + dt * (R[6] * fx + R[7] * fy + R[8] * fz + c[8])
    return R + (x[9] + dt * vx, x[10] + dt * vy, x[11] + dt * vz, vx, vy, vz)


def _rate_at(t_ns: int, s0: tuple, s1: tuple) -> tuple:
    """The six rates linearly interpolated at t_ns between samples s0 and s1 (held outside them)."""
    if t_ns <= s0[0] or s1[0] <= s0[0]:
        return s0[1:]
    if t_ns >= s1[0]:
        return s1[1:]
    u = (t_ns - s0[0]) / (s1[0] - s0[0])
    return tuple(a + u * (b - a) for a, b in zip(s0[1:], s1[1:]))


def step_midpoint(x: tuple, c: tuple, t0_ns: int, t1_ns: int, s0: tuple, s1: tuple) -> tuple:
    dt = (t1_ns - t0_ns) * NS
    g0x, g0y, g0z, a0x, a0y, a0z = _rate_at(t0_ns, s0, s1)
    g1x, g1y, g1z, a1x, a1y, a1z = _rate_at(t1_ns, s0, s1)
    R = rotate(x, (0.5 * (g0x + g1x) - c[0]) * dt, (0.5 * (g0y + g1y) - c[1]) * dt, (0.5 * (g0z + g1z) - c[2]) * dt)
    f0x, f0y, f0z = a0x - c[3], a0y - c[4], a0z - c[5]
    f1x, f1y, f1z = a1x - c[3], a1y - c[4], a1z - c[5]
    # mean of R0 f0 + g and R1 f1 + g
    mx = 0.5 * (x[0] * f0x + x[1] * f0y + x[2] * f0z + R[0] * f1x + R[1] * f1y + R[2] * f1z) + c[6]
    my = 0.5 * (x[3] * f0x + x[4] * f0y + x[5] * f0z + R[3] * f1x + R[4] * f1y + R[5] * f1z) + c[7]
    mz = 0.5 * (x[6] * f0x + x[7] * f0y + x[8] * f0z + R[6] * f1x + R[7] * f1y + R[8] * f1z) + c[8]
    h = 0.5 * dt * dt
    return R + (
        x[9] + dt * x[12] + h * mx, x[10] + dt * x[13] + h * my, x[11] + dt * x[14] + h * mz,
        x[12] + dt * mx, x[13] + dt * my, x[14] + dt * mz,
    )


def measured(t1_ns: int, s0: tuple, s1: tuple, max_gap_ns: int) -> bool:
    """Whether the IMU measured an interval ending at t1 between samples s0, s1 (at or before it and after
    it, or the newest twice): not across a gap longer than max_gap_ns, nor that far past the newest."""
    return s1[0] - s0[0] <= max_gap_ns and t1_ns - s1[0] <= max_gap_ns


INTEGRATOR_STEPS = {"paper": step_paper, "midpoint": step_midpoint}


def propagate(step, x: tuple, c: tuple, t_ns: int, samples: list, states: list, start: int) -> tuple:
    """Re-propagate from state `x` at `t_ns` through `samples[start:]`, writing `states[start:]`.

    `samples[start]` is the first sample after `t_ns`; `samples[start - 1]` (if any) the one at or
    before it. Returns the state at the newest sample (or `x` when there is none after `t_ns`).
    """
    prev = samples[start - 1] if start > 0 else None
    for i in range(start, len(samples)):
        s = samples[i]
        x = step(x, c, t_ns, s[0], prev if prev is not None else s, s)
        states[i] = x
        t_ns, prev = s[0], s
    return x
