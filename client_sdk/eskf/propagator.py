"""Covariance propagation over one IMU interval (the nominal state uses `client_sdk.propagation`).

Continuous-time error dynamics, with w = w_m - b_g and a = a_m - b_a (body frame):

    d_theta' = -[w]x d_theta - d_bg - n_g        d_p' = d_v
    d_v'     = -R [a]x d_theta - R d_ba + d_g - R n_a
    d_bg'    = n_wg        d_ba' = n_wa         d_g' = 0       d_td' = 0

discretised to first order, Phi = I + A dt, Q = diag(sigma^2 dt) with Kalibr's densities. The 36
non-trivial entries of Phi are written with one indexed assignment: the whole step costs a few microseconds,
two 19x19 products included.
"""

from __future__ import annotations

import numpy as np

from client_sdk.eskf.options import FilterOptions
from client_sdk.eskf.state import N
from client_sdk.propagation import NS

_IDENTITY = np.eye(N)


def _flat(pairs) -> list[int]:
    return [r * N + c for r, c in pairs]


_PHI_INDEX = np.array(
    _flat((r, c) for r in range(3) for c in range(3))  # theta-theta
    + _flat((k, 9 + k) for k in range(3))  # theta-bg
    + _flat((3 + k, 6 + k) for k in range(3))  # p-v
    + _flat((6 + r, c) for r in range(3) for c in range(3))  # v-theta
    + _flat((6 + r, 12 + c) for r in range(3) for c in range(3))  # v-ba
    + _flat((6 + k, 15 + k) for k in range(3)))  # v-g
_Q_EVERY = 20  # samples between updates of Q from the in-use noise estimate
# The estimate scatters by a few % over its window; taking max(yaml, estimate) as it is would bias the
# densities up (a simulated Pixel 2's GT NEES 5.8 for 6). Only an IMU showing clearly more than its yaml
# replaces it.
_RAISE_ABOVE = 1.2
_Q_INDEX = np.array(_flat((k, k) for k in (0, 1, 2, 6, 7, 8, 9, 10, 11, 12, 13, 14)))


class CovariancePropagator:
    """Phi P Phi^T + Q for one interval; the noise part from the options, raised by `observe` to what
    the IMU shows in use when `FilterOptions.adapt_imu_noise` is on."""

    def __init__(self, options: FilterOptions) -> None:
        k = options.noise_inflation
        self._densities = (k * options.gyroscope_noise_density, k * options.accelerometer_noise_density)
        self._walks = (k * options.gyroscope_random_walk, k * options.accelerometer_random_walk)
        self._adapt = options.adapt_imu_noise
        self._alpha = 1.0 / max(options.noise_window_samples, 1)
        self._n2 = [0.0, 0.0]  # running estimate of the squared white-noise density, gyro and accel
        self._last: tuple = (None, None, None)  # the three samples before the next
        self._seen = 0
        self._phi = _IDENTITY.copy()
        self._set_q(*self._densities)

    def _set_q(self, gyro_density: float, accel_density: float) -> None:
        self._q_dt = (0.0, None)  # Q for the last dt, recomputed when either changes
        self._q_density = np.array([gyro_density ** 2] * 3 + [accel_density ** 2] * 3 + [self._walks[0] ** 2] * 3
                                   + [self._walks[1] ** 2] * 3)

    def observe(self, sample: tuple) -> None:
        """Take in one new IMU sample. The noise that matters is what the midpoint integrator sees: the
        means m[k] = (s[k] + s[k+1]) / 2 of consecutive samples. White noise of density n at rate r
        makes their second difference m[k+1] - 2 m[k] + m[k-1] = (s[k+2] - s[k+1] - s[k] + s[k-1]) / 2
        n^2 r in mean square per axis, smooth motion adds next to nothing to it (a simulated Pixel 2
        reads its yaml), and vibration near the Nyquist rate, which the means cancel, adds little
        (EuRoC's rotors; the CHANGELOG has what it did to that experiment). A vibrating device still
        shows far more than its datasheet's n, and the filter must believe it."""
        if not self._adapt:
            return
        s0, s1, s2 = self._last
        self._last = (s1, s2, sample)
        if s0 is None:
            return
        dt = (sample[0] - s0[0]) * NS / 3.0
        if dt <= 0:
            return
        a, n2 = self._alpha, self._n2
        d = [sample[i] - s2[i] - s1[i] + s0[i] for i in range(1, 7)]  # twice the means' second difference
        n2[0] += a * ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) * dt / 12.0 - n2[0])  # -> n^2 (mean of 3 axes)
        n2[1] += a * ((d[3] * d[3] + d[4] * d[4] + d[5] * d[5]) * dt / 12.0 - n2[1])
        self._seen += 1
        if self._seen % _Q_EVERY == 0:  # Q follows the estimate ten times a second, not every sample
            self._set_q(*(seen if seen > _RAISE_ABOVE * base else base
                          for seen, base in zip((n2[0] ** 0.5, n2[1] ** 0.5), self._densities)))

    @property
    def densities(self) -> tuple[float, float]:
        """The white-noise densities (gyro, accel) in use."""
        return float(self._q_density[0] ** 0.5), float(self._q_density[3] ** 0.5)

    def transition(self, x: tuple, dt: float, w: tuple, a: tuple) -> np.ndarray:
        """Phi for an interval of dt seconds ending at nominal x, with bias-corrected rates w, a."""
        w0, w1, w2 = w[0] * dt, w[1] * dt, w[2] * dt
        a0, a1, a2 = a
        r = x[0:9]
        m = []  # -R [a]x dt, row-major
        for i in range(3):
            ri0, ri1, ri2 = r[3 * i], r[3 * i + 1], r[3 * i + 2]
            m += [-(ri1 * a2 - ri2 * a1) * dt, -(ri2 * a0 - ri0 * a2) * dt, -(ri0 * a1 - ri1 * a0) * dt]
        values = ([1.0, w2, -w1, -w2, 1.0, w0, w1, -w0, 1.0, -dt, -dt, -dt, dt, dt, dt] + m
                  + [-e * dt for e in r] + [dt, dt, dt])
        phi = self._phi
        phi.ravel()[_PHI_INDEX] = values  # a view: ~1 us less than np.put with a list
        return phi

    @property
    def last_transition(self) -> np.ndarray:
        """Phi of the last `step` with a positive interval (a view, overwritten by the next)."""
        return self._phi

    def step(self, cov: np.ndarray, x: tuple, c: tuple, t0_ns: int, t1_ns: int, s0: tuple, s1: tuple) -> np.ndarray:
        """The covariance at t1 from the one at t0; s0, s1 the raw IMU samples around the interval."""
        dt = (t1_ns - t0_ns) * NS
        if dt <= 0:
            return cov
        w = (0.5 * (s0[1] + s1[1]) - c[0], 0.5 * (s0[2] + s1[2]) - c[1], 0.5 * (s0[3] + s1[3]) - c[2])
        a = (0.5 * (s0[4] + s1[4]) - c[3], 0.5 * (s0[5] + s1[5]) - c[4], 0.5 * (s0[6] + s1[6]) - c[5])
        phi = self.transition(x, dt, w, a)
        out = phi @ cov @ phi.T
        if self._q_dt[0] != dt:
            self._q_dt = (dt, self._q_density * dt)
        out.ravel()[_Q_INDEX] += self._q_dt[1]
        return out
