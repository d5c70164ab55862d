"""The integrated autocorrelation time of a series: how many samples one independent sample is worth.

The mean of N correlated samples varies as much as the mean of N / tau independent ones. Two users:
the filter's still-start initialisation (the standard error of a window's mean IMU reading, when
vibration or tremor makes consecutive samples alike) and the NEES interval of a run
(`flextrack.evaluation.consistency`). numpy only: the client SDK imports it.
"""

from __future__ import annotations

import numpy as np


def autocorrelation_time(series: np.ndarray, window_factor: float = 5.0) -> float:
    """Integrated autocorrelation time (>= 1) of a 1-D series, with Sokal's automatic window (the
    smallest lag M with M >= window_factor * tau(M))."""
    x = np.asarray(series, float) - np.mean(series)
    n = len(x)
    if n < 3 or not np.any(x):
        return 1.0
    spectrum = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(spectrum * np.conj(spectrum))[:n]
    rho = acf / acf[0]
    tau = 1.0 + 2.0 * np.cumsum(rho[1:])
    m = np.arange(1, n)
    inside = m >= window_factor * tau
    return float(max(1.0, tau[np.argmax(inside)] if inside.any() else tau[-1]))


def standard_error_of_mean(samples: np.ndarray) -> float:
    """The standard error of the mean of (N, k) samples, per axis (RMS over the k axes), with each
    axis's N counted as N / tau."""
    a = np.asarray(samples, float)
    n = len(a)
    if n < 2:
        return float("inf")
    variances = [np.var(a[:, k]) * autocorrelation_time(a[:, k]) / n for k in range(a.shape[1])]
    return float(np.sqrt(np.mean(variances)))
