"""Is a tracker's mean NEES consistent with chi-square, when its frames are not independent?

Consecutive frames of one run share the filter's state, so their NEES values are correlated: the mean
of N of them varies as much as the mean of N / tau independent ones, tau being the series' integrated
autocorrelation time. The 95 % interval of the mean is then that of chi-square(dof * n_eff) / n_eff with
n_eff = N / tau (tau estimated with Sokal's automatic window: the smallest M with M >= 5 tau(M)). With
independent frames n_eff = N and this is the usual interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


@dataclass(frozen=True)
class MeanInterval:
    n_eff: float
    lo: float
    hi: float

    def holds(self, mean: float) -> bool:
        return bool(self.lo <= mean <= self.hi)


def autocorrelation_time(series: np.ndarray, window_factor: float = 5.0) -> float:
    """Integrated autocorrelation time (>= 1) of a 1-D series."""
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


def nees_mean_interval(nees: np.ndarray, dof: int = 6, level: float = 0.95) -> MeanInterval:
    """The interval the mean of `nees` lies in with probability `level` for a consistent estimator."""
    nees = np.asarray(nees, float)
    nees = nees[np.isfinite(nees)]
    if len(nees) == 0:
        return MeanInterval(0.0, float("nan"), float("nan"))
    n_eff = len(nees) / autocorrelation_time(nees)
    a = (1.0 - level) / 2.0
    lo, hi = stats.chi2.ppf([a, 1.0 - a], dof * n_eff) / n_eff
    return MeanInterval(float(n_eff), float(lo), float(hi))
