"""Is a tracker's mean NEES consistent with chi-square, when its frames are not independent?

Consecutive frames of one run share the filter's state, so their NEES values are correlated: the mean
of N of them varies as much as the mean of n_eff independent ones, and its 95 % interval is that of
chi-square(dof * n_eff) / n_eff (with independent frames n_eff = N, the usual interval). Two ways to
n_eff:

- `model_nees_interval`, from the filter's own error dynamics (`client_sdk.eskf.error_dynamics`): for
  Gaussian errors cov(NEES_t, NEES_s) = 2 |C_ts|_F^2, C_ts the two frames' whitened error
  cross-covariance, so Var(mean) = 2 sum_ts |C_ts|^2 / N^2 and n_eff = 2 dof / Var(mean). This sees
  correlations longer than the run (the rotation and the gyro bias of a device that hardly turns).
- `nees_mean_interval`, from the NEES series' own integrated autocorrelation time tau, n_eff = N / tau
  (`flextrack.autocorrelation`): for trackers that keep no such record. It sees only correlations
  well inside the run, and so gives too narrow an interval when they are not.
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
    """The interval the mean of `nees` lies in with probability `level` for a consistent estimator, n_eff from
    the series' own autocorrelation."""
    nees = np.asarray(nees, float)
    nees = nees[np.isfinite(nees)]
    if len(nees) == 0:
        return MeanInterval(0.0, float("nan"), float("nan"))
    return _interval(len(nees) / autocorrelation_time(nees), dof, level)


def model_nees_interval(frames: list[tuple[int, np.ndarray]], dynamics, dof: int = 6,
                        level: float = 0.95) -> MeanInterval:
    """As `nees_mean_interval`, n_eff from the filter's error dynamics (an `ErrorDynamics`): `frames` are the
    scored frames' (camera time, reported 6x6 covariance), each of which the record must hold."""
    n = len(frames)
    if n == 0:
        return MeanInterval(0.0, float("nan"), float("nan"))
    links = [dynamics.frames[t_ns] for t_ns, _ in frames]
    anchor_of = np.array([anchor for anchor, _ in links])
    L = np.linalg.cholesky(np.stack([covariance for _, covariance in frames]))
    A = np.linalg.solve(L, np.stack([pose_map for _, pose_map in links]))  # whitened pose maps, (n, dof, N)
    total = float(n * dof)  # each frame with itself: |I_dof|^2
    weights = {}  # per anchor, S_k = sum of A_t^T A_t over its frames
    for k in np.unique(anchor_of):
        A_k = A[anchor_of == k]
        P = dynamics.anchors[k][1]
        S = np.einsum("fij,fik->jk", A_k, A_k)
        C = A_k @ P @ A_k.transpose(0, 2, 1)  # each frame's own C_tt, left out of the pairs below
        total += float(np.einsum("ij,jk,kl,li->", S, P, S, P)) - float(np.sum(C * C))
        weights[int(k)] = S
    # frames on anchors k > j: C_ts = A_t M_kj P_j A_s^T with M_kj = Psi_k ... Psi_j+1, so the pairs add up to
    # tr(Y_j P_j S_j P_j), Y_j = sum_k M_kj^T S_k M_kj = Psi_j+1^T (S_j+1 + Y_j+1) Psi_j+1: one pass back
    zero = np.zeros((A.shape[2], A.shape[2]))
    Y = zero
    for j in range(len(dynamics.anchors) - 1, -1, -1):
        psi, P = dynamics.anchors[j]
        if j in weights:
            total += 2.0 * float(np.einsum("ij,jk,kl,li->", Y, P, weights[j], P))
        Y = zero if psi is None else psi.T @ (weights.get(j, zero) + Y) @ psi  # None: a (re)start, no link
    return _interval(n * n * dof / total, dof, level)


def _interval(n_eff: float, dof: int, level: float) -> MeanInterval:
    a = (1.0 - level) / 2.0
    lo, hi = stats.chi2.ppf([a, 1.0 - a], dof * n_eff) / n_eff
    return MeanInterval(float(n_eff), float(lo), float(hi))
