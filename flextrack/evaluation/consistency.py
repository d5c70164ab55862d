"""Is a tracker's mean NEES consistent with chi-square, when its frames are not independent?

Consecutive frames of one run share the filter's state, so their NEES values are correlated: the mean
of N of them varies as much as the mean of N / tau independent ones, tau being the series' integrated
autocorrelation time. The 95 % interval of the mean is then that of chi-square(dof * n_eff) / n_eff with
n_eff = N / tau (`flextrack.autocorrelation`). With independent frames n_eff = N and this is the usual
interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from flextrack.autocorrelation import autocorrelation_time


@dataclass(frozen=True)
class MeanInterval:
    n_eff: float
    lo: float
    hi: float

    def holds(self, mean: float) -> bool:
        return bool(self.lo <= mean <= self.hi)


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
