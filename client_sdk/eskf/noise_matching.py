"""The IMU's effective noise from the answers' innovations (covariance matching).

A phone's gyroscope and accelerometer err far more in use than white noise of their datasheet density:
scale and misalignment errors, a filtered and resampled stream, irregular timestamps, a lever arm. All
of it shows in the innovations: between two answers tau_{k-1} and tau_k (dt apart) white noise of
density q adds about 3 q^2 dt to the trace of the rotation block of S = H P H^T + Sigma (gyro) and
q^2 dt^3 to the translation block's (accelerometer). So each answer gives a sample of the squared
density, from its residual r:

    e_k = |r_rot|^2 - (tr S_rot - 3 q_now^2 dt),     e_k = b_k q^2 + zero-mean noise,   b_k = 3 dt

(dt^3 and the translation block for the accelerometer), and q^2 is their weighted least-squares fit,
weights 1 / var(e_k) = 1 / (2 tr(S_block^2)) (Gaussian residuals: an anisotropic block scatters
more than an isotropic one of the same trace), with an exponential memory of
`noise_match_answers` answers. The filter uses max(yaml density, the fit less 2 standard errors: the
least noise the answers insist on, a lower confidence bound). The answers' own noise hides a good
IMU's (a simulated Pixel 2's gyro: standard error ~100x its density), so an IMU as good as its yaml is
nearly always left alone, and the density moves continuously (a switch at a significance level made
it flicker between the yaml's and the fit's). The bound trades the phones' consistency against the
simulator's: on the phone recording nexus5_ar_b (the one it was chosen on; nexus5_ar_a held out) mean
NEES 12.5 with 2, 10.3 with 1.5, 9.5 with 1; on `flextrack experiment filter` (10 seeds) 1.5 raised
the peer cells' jitter by a third and their error by 4-7 %, 2 leaves them within their noise.
Costs a few scalar operations per answer, nothing per IMU sample.
"""

from __future__ import annotations

import math

import numpy as np

MIN_ANSWERS = 20  # the fit is used from this many answers on (one answer on the gate is no evidence)
SE_BELOW = 2.0  # the density used: the fit less this many standard errors (see above)


class NoiseMatcher:
    """The running fit of one density (gyro from the rotation block, accelerometer from the translation's)."""

    def __init__(self, memory_answers: float, power: int) -> None:
        self._decay = 1.0 - 1.0 / max(memory_answers, 1.0)
        self._power = power  # dt's power in b: 1 for the gyro, 3 for the accelerometer
        self._num = 0.0  # sum of w b e
        self._den = 0.0  # sum of w b^2
        self._count = 0.0  # answers, with the same memory
        self.fit = 0.0  # the squared density the answers show (unbiased, scattered)
        self.density = 0.0  # the fit less two standard errors, the least the answers insist on (0 at most)

    @property
    def early_fit(self) -> float | None:
        """The squared density's fit from the first answer on (`fit` waits for MIN_ANSWERS; None before any)."""
        return None if self._den <= 0 else self._num / self._den

    def add(self, r2: float, trace_s: float, density_now: float, dt: float, trace_s2: float | None = None) -> None:
        """One answer: |r|^2 and tr(S) of its block, the density S was built with, the interval since the
        last answer; `trace_s2` tr(S_block^2) (default: as for an isotropic block, tr(S)^2 / 3)."""
        if not (dt > 0 and trace_s > 0 and math.isfinite(r2)):
            return
        dims = 3.0 if self._power == 1 else 1.0
        b = dims * dt ** self._power
        e = r2 - (trace_s - density_now ** 2 * b)
        w = 0.5 / (trace_s * trace_s / 3.0 if trace_s2 is None else trace_s2)  # 1 / var(|r|^2) = 1 / (2 tr S^2)
        self._num = self._num * self._decay + w * b * e
        self._den = self._den * self._decay + w * b * b
        self._count = self._count * self._decay + 1.0
        if self._count < MIN_ANSWERS:
            return
        self.fit = self._num / self._den
        self.density = math.sqrt(max(self.fit - SE_BELOW / math.sqrt(self._den), 0.0))


def blocks(r: np.ndarray, S: np.ndarray) -> list[tuple[float, float, float]]:
    """[(|r_b|^2, tr S_b, tr S_b^2)] for the rotation block and the translation block of an answer's residual
    and innovation covariance (on Python floats: a dozen numpy calls cost more than the update's own)."""
    rs, Ss = r.tolist(), S.tolist()
    out = []
    for lo in (0, 3):
        rows = [Ss[i][lo:lo + 3] for i in range(lo, lo + 3)]
        out.append((sum(x * x for x in rs[lo:lo + 3]), rows[0][0] + rows[1][1] + rows[2][2],
                    sum(x * x for row in rows for x in row)))
    return out
