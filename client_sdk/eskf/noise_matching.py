"""The IMU's effective noise from the answers' innovations (covariance matching).

A phone's gyroscope and accelerometer err far more in use than white noise of their datasheet density:
scale and misalignment errors, a filtered and resampled stream, irregular timestamps, a lever arm. All
of it shows in the innovations: between two answers tau_{k-1} and tau_k (dt apart) white noise of
density q adds about 3 q^2 dt to the trace of the rotation block of S = H P H^T + Sigma (gyro) and
q^2 dt^3 to the translation block's (accelerometer). So each answer gives a sample of the squared
density, from its residual r:

    e_k = |r_rot|^2 - (tr S_rot - 3 q_now^2 dt),     e_k = b_k q^2 + zero-mean noise,   b_k = 3 dt

(dt^3 and the translation block for the accelerometer), and q^2 is their weighted least-squares fit,
weights 1 / var(e_k) ~ 3 / (2 tr(S)^2) (a scaled chi-square of 3 dof), with an exponential memory of
`noise_match_answers` answers. The filter uses max(yaml density, the fit less one standard error): an
IMU as good as its yaml (the simulator's) is left nearly alone, and the density moves continuously
(a switch at a significance level made it flicker between the yaml's and the fit's).
Costs a few scalar operations per answer, nothing per IMU sample.
"""

from __future__ import annotations

import math

import numpy as np

MIN_ANSWERS = 20  # the fit is used from this many answers on (one answer on the gate is no evidence)


class NoiseMatcher:
    """The running fit of one density (gyro from the rotation block, accelerometer from the translation's)."""

    def __init__(self, memory_answers: float, power: int) -> None:
        self._decay = 1.0 - 1.0 / max(memory_answers, 1.0)
        self._power = power  # dt's power in b: 1 for the gyro, 3 for the accelerometer
        self._num = 0.0  # sum of w b e
        self._den = 0.0  # sum of w b^2
        self._count = 0.0  # answers, with the same memory
        self.density = 0.0  # the fit less one standard error (0 until it has one)

    def add(self, r2: float, trace_s: float, density_now: float, dt: float) -> None:
        """One answer: |r|^2 and tr(S) of its block, the density S was built with, the interval since the
        last answer."""
        if not (dt > 0 and trace_s > 0 and math.isfinite(r2)):
            return
        dims = 3.0 if self._power == 1 else 1.0
        b = dims * dt ** self._power
        e = r2 - (trace_s - density_now ** 2 * b)
        w = 1.5 / (trace_s * trace_s)
        self._num = self._num * self._decay + w * b * e
        self._den = self._den * self._decay + w * b * b
        self._count = self._count * self._decay + 1.0
        if self._count < MIN_ANSWERS:
            return
        fit = self._num / self._den
        se = 1.0 / math.sqrt(self._den)
        self.density = math.sqrt(max(fit - se, 0.0))


def blocks(r: np.ndarray, S: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """((|r_rot|^2, tr S_rot), (|r_t|^2, tr S_t)) of an answer's residual and innovation covariance."""
    return ((float(r[0:3] @ r[0:3]), float(S[0, 0] + S[1, 1] + S[2, 2])),
            (float(r[3:6] @ r[3:6]), float(S[3, 3] + S[4, 4] + S[5, 5])))
