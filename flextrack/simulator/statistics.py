"""Allan deviation of IMU signals, to check the synthesized noise against its densities.

For white noise of density N the Allan deviation is N / sqrt(tau) (so N at tau = 1 s); a bias
random walk of density K adds K * sqrt(tau / 3). `expected_adev` is the sum of both, in quadrature.
"""

from __future__ import annotations

import numpy as np


def allan_deviation(samples: np.ndarray, rate_hz: float, taus_s: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of (N,) or (N, k) samples at the given cluster times (s)."""
    y = np.asarray(samples, float)
    y = y[:, None] if y.ndim == 1 else y
    n = len(y)
    if taus_s is None:
        taus_s = np.logspace(np.log10(2.0 / rate_hz), np.log10(n / rate_hz / 10), 40)
    m = np.unique(np.clip(np.round(np.asarray(taus_s) * rate_hz).astype(int), 1, (n - 1) // 2))
    theta = np.vstack([np.zeros((1, y.shape[1])), np.cumsum(y, axis=0)]) / rate_hz
    adev = np.empty((len(m), y.shape[1]))
    for i, mi in enumerate(m):
        tau = mi / rate_hz
        d = theta[2 * mi:] - 2 * theta[mi:-mi] + theta[:-2 * mi]
        adev[i] = np.sqrt(np.mean(d**2, axis=0) / (2 * tau**2))
    return m / rate_hz, adev


def expected_adev(taus_s: np.ndarray, noise_density: float, random_walk: float) -> np.ndarray:
    taus_s = np.asarray(taus_s, float)
    return np.sqrt(noise_density**2 / taus_s + random_walk**2 * taus_s / 3)
