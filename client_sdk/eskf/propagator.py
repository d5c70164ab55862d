"""Covariance propagation over one IMU interval (the nominal state uses `client_sdk.propagation`).

Continuous-time error dynamics, with w = w_m - b_g and a = a_m - b_a (body frame):

    d_theta' = -[w]x d_theta - d_bg - n_g        d_p' = d_v
    d_v'     = -R [a]x d_theta - R d_ba + d_g - R n_a
    d_bg'    = n_wg        d_ba' = n_wa         d_g' = 0       d_td' = 0

discretised to first order, Phi = I + A dt, Q = diag(sigma^2 dt) with Kalibr's densities, plus the
gyro's scale-and-misalignment error: a constant M (each entry sigma_M, `gyroscope_scale_error`) errs by
M w, which turns the orientation by about M w T over the T the IMU alone carries it (from one answer's
capture to the next answer's arrival), of variance sigma_M^2 |w|^2 T^2 per axis: as a white density
over T, sigma_M^2 |w|^2 T, added to the gyro's on the orientation's diagonal each sample (T a running
mean). The 36
non-trivial entries of Phi are kept in one array and only those that changed are written (an indexed
assignment each): the whole step costs a few microseconds, two 19x19 products included.
"""

from __future__ import annotations

import numpy as np

from client_sdk.eskf.options import FilterOptions
from client_sdk.eskf.state import N
from client_sdk.propagation import NS

_IDENTITY = np.eye(N)


def _flat(pairs) -> list[int]:
    return [r * N + c for r, c in pairs]


# Phi = I + A dt has 36 non-trivial entries. 24 change with every sample (the rotation's off-diagonal,
# -R [a]x dt and -R dt); the 9 of +-dt only when the interval does; the diagonal stays 1.
_PHI_SAMPLE = np.array(
    _flat((r, c) for r in range(3) for c in range(3) if r != c)  # theta-theta
    + _flat((6 + r, c) for r in range(3) for c in range(3))  # v-theta
    + _flat((6 + r, 12 + c) for r in range(3) for c in range(3)))  # v-ba
_PHI_DT = np.array(
    _flat((k, 9 + k) for k in range(3))  # theta-bg: -dt
    + _flat((3 + k, 6 + k) for k in range(3))  # p-v: dt
    + _flat((6 + k, 15 + k) for k in range(3)))  # v-g: dt
_Q_EVERY = 20  # samples between updates of Q from the in-use noise estimate
# The estimate scatters by a few % over its window; taking max(yaml, estimate) as it is would bias the
# densities up (a simulated Pixel 2's GT NEES 5.8 for 6). Only an IMU showing clearly more than its yaml
# replaces it.
_RAISE_ABOVE = 1.2
_Q_INDEX = np.array(_flat((k, k) for k in (0, 1, 2, 6, 7, 8, 9, 10, 11, 12, 13, 14)))
_HORIZON_START_S = 0.1  # the scale error's T before the first answer interval
_HORIZON_BOUNDS_S = (0.01, 0.5)  # ... and the span an interval is clipped to
_HORIZON_WEIGHT = 0.1  # each answer interval's weight in T's running mean


class CovariancePropagator:
    """Phi P Phi^T + Q for one interval; the noise part from the options, raised by `observe` to what
    the IMU shows in use when `FilterOptions.adapt_imu_noise` is on."""

    def __init__(self, options: FilterOptions) -> None:
        k = options.noise_inflation
        self._densities = (k * options.gyroscope_noise_density, k * options.accelerometer_noise_density)
        self._walks = (k * options.gyroscope_random_walk, k * options.accelerometer_random_walk)
        self._adapt = options.adapt_imu_noise
        self._max_gap_s = options.max_imu_gap_s
        alpha = 1.0 / max(options.noise_window_samples, 1)
        # n2 <- (1 - alpha) n2 + alpha seen, _Q_EVERY times: the old n2's factor and each new value's
        self._decay = (1.0 - alpha) ** _Q_EVERY
        self._weights = alpha * (1.0 - alpha) ** np.arange(_Q_EVERY - 1, -1, -1)
        self._seen = self._densities  # the densities the IMU shows (observe), never below the yaml's
        self._matched = (0.0, 0.0)  # the densities the answers' innovations show (`match`)
        self._n2 = np.zeros(2)  # running estimate of the squared white-noise density, gyro and accel
        self._pending: list[tuple] = []  # the samples not yet in it, and the three before them
        self._phi = _IDENTITY.copy()
        self._phi_dt = 0.0  # the interval the +-dt entries of _phi hold
        self._scale2 = options.gyroscope_scale_error ** 2
        self._horizon_s = _HORIZON_START_S  # T, the interval the IMU alone carries the orientation
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
        shows far more than its datasheet's n, and the filter must believe it.

        The running mean (one exponential average per sample) is only read when Q is set, every
        _Q_EVERY samples, so it is brought up to date then, for all of them at once. A second difference
        across a gap of the stream (an interval over `max_imu_gap_s`) measures the motion during the gap, not
        the noise: it counts as the estimate so far (`nexus5_ar_a`: one across its 23.7 s gap raised the
        accelerometer's density ~40-fold, and the pose stayed too uncertain for FINE for 2 s after the samples
        came back)."""
        if not self._adapt:
            return
        pending = self._pending
        pending.append(sample)
        if len(pending) < _Q_EVERY + 3:
            return
        s = np.array(pending)
        self._pending = pending[-3:]
        dt = (s[3:, 0] - s[:-3, 0]) * (NS / 3.0)  # the mean interval over each second difference
        d = s[3:, 1:] - s[2:-1, 1:] - s[1:-2, 1:] + s[:-3, 1:]  # twice the means' second differences
        d2 = d * d
        seen = np.stack([d2[:, 0:3].sum(axis=1), d2[:, 3:6].sum(axis=1)]) * (dt / 12.0)  # -> n^2 per sample
        steps = np.diff(s[:, 0]) * NS
        across = np.maximum(np.maximum(steps[:-2], steps[1:-1]), steps[2:]) > self._max_gap_s
        if across.any():
            seen[:, across] = self._n2[:, None]
        self._n2 = self._n2 * self._decay + seen @ self._weights  # the averages, sample by sample, at once
        self._seen = tuple(est if est > _RAISE_ABOVE * base else base
                           for est, base in zip(np.sqrt(self._n2).tolist(), self._densities))
        self._set_q(*map(max, self._seen, self._matched))

    def match(self, gyro_density: float, accel_density: float) -> None:
        """Raise the densities to what the answers' innovations show (`eskf.noise_matching`; 0: no raise)."""
        if (gyro_density, accel_density) == self._matched:  # the common case: Q (and its cache) unchanged
            return
        self._matched = (gyro_density, accel_density)
        self._set_q(*map(max, self._seen, self._matched))

    def note_answer_interval(self, dt: float) -> None:
        """One more span (s) the IMU alone carried the pose, from an answer's capture to the next one's arrival,
        measured across: the scale error's horizon T."""
        lo, hi = _HORIZON_BOUNDS_S
        self._horizon_s += _HORIZON_WEIGHT * (min(max(dt, lo), hi) - self._horizon_s)

    @property
    def densities(self) -> tuple[float, float]:
        """The white-noise densities (gyro, accel) in use."""
        return float(self._q_density[0] ** 0.5), float(self._q_density[3] ** 0.5)

    def transition(self, x: tuple, dt: float, w: tuple, a: tuple) -> np.ndarray:
        """Phi for an interval of dt seconds ending at nominal x, with bias-corrected rates w, a."""
        w0, w1, w2 = w[0] * dt, w[1] * dt, w[2] * dt
        a0, a1, a2 = a[0] * dt, a[1] * dt, a[2] * dt
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = x[0:9]
        flat = self._phi.ravel()  # a view
        flat[_PHI_SAMPLE] = (
            w2, -w1, -w2, w0, w1, -w0,  # I - [w dt]x, off the diagonal
            r02 * a1 - r01 * a2, r00 * a2 - r02 * a0, r01 * a0 - r00 * a1,  # -R [a dt]x
            r12 * a1 - r11 * a2, r10 * a2 - r12 * a0, r11 * a0 - r10 * a1,
            r22 * a1 - r21 * a2, r20 * a2 - r22 * a0, r21 * a0 - r20 * a1,
            -r00 * dt, -r01 * dt, -r02 * dt, -r10 * dt, -r11 * dt, -r12 * dt, -r20 * dt, -r21 * dt, -r22 * dt)
        if dt != self._phi_dt:
            flat[_PHI_DT] = (-dt, -dt, -dt, dt, dt, dt, dt, dt, dt)
            self._phi_dt = dt
        return self._phi

    @property
    def last_transition(self) -> np.ndarray:
        """Phi of the last `step` with a positive interval (a view, overwritten by the next)."""
        return self._phi

    @property
    def walks(self) -> tuple[float, float]:
        """The bias random walks (gyro rad/s^2/sqrt(Hz), accel m/s^3/sqrt(Hz))."""
        return self._walks

    def step(self, cov: np.ndarray, x: tuple, c: tuple, t0_ns: int, t1_ns: int, s0: tuple, s1: tuple) -> np.ndarray:
        """The covariance at t1 from the one at t0; s0, s1 the raw IMU samples around the interval (measured:
        a gap in the IMU's stream is `eskf.coasting`'s)."""
        dt = (t1_ns - t0_ns) * NS
        if dt <= 0:
            return cov
        w = (0.5 * (s0[1] + s1[1]) - c[0], 0.5 * (s0[2] + s1[2]) - c[1], 0.5 * (s0[3] + s1[3]) - c[2])
        a = (0.5 * (s0[4] + s1[4]) - c[3], 0.5 * (s0[5] + s1[5]) - c[4], 0.5 * (s0[6] + s1[6]) - c[5])
        phi = self.transition(x, dt, w, a)
        out = np.dot(np.dot(phi, cov), phi.T)  # np.dot: ~0.3 us less per 19x19 product than @
        if self._q_dt[0] != dt:
            q = np.zeros((N, N))
            q.ravel()[_Q_INDEX] = self._q_density * dt
            self._q_dt = (dt, q)
        out += self._q_dt[1]  # a dense add: cheaper than an indexed one
        if self._scale2:  # the scale error's share, which moves with the rate (see the module's docstring)
            v = self._scale2 * self._horizon_s * (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * dt
            out[0, 0] += v
            out[1, 1] += v
            out[2, 2] += v
        return out
