"""The backend-pose updater: a T_CO measurement with its 6x6 covariance, applied at its own time.

Measurement model (the wire convention of `flextrack.wire`: rotation error first, camera frame):
T_CO = T_CB T_OB^-1, so R_CO = R_CB R_OB^T and t_CO = t_CB - R_CO p_OB. The residual

    r = ( Log(R_CO_meas R_CO^T),  t_CO_meas - t_CO )

is, to first order in the error state, r = H dx + n with

    H[:, d_theta] = ( -R_CB ; -[R_CO p_OB]x R_CB )     H[:, d_p] = ( 0 ; -R_CO )
    H[:, d_td]    = H[:, d_theta] w + H[:, d_p] v        (the pose at t + d_td)

and n the backend's error, covariance Sigma, to which the second-order products of the time offset
with the rates it multiplies are added (`offset_terms`; the offset is not corrected while the motion
does not show it). An answer whose r^T S^-1 r (S = H P H^T + Sigma) exceeds the chi-square gate is
rejected; otherwise the Kalman gain, the Joseph-form covariance and the injection of K r into the
nominal state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client_sdk.eskf.state import BG, TD, TH, FilterState, N, P, V, inject
from flextrack.geometry import so3

_I = np.eye(N)


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class UpdateResult:
    accepted: bool
    chi2: float  # r^T S^-1 r
    state: FilterState | None  # the corrected state when accepted
    td: float  # the corrected time offset (s)
    closed_loop: np.ndarray | None = None  # I - K H, what the update does to the error (when accepted)
    residual: np.ndarray | None = None  # r, and its covariance S (for `eskf.noise_matching`)
    S: np.ndarray | None = None


def pose_jacobian(x: tuple, R_CB: np.ndarray, w: tuple, v: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_CO, t_CO without t_CB, H): the predicted camera-frame pose parts and the 6xN Jacobian."""
    R_OB = np.array(x[0:9]).reshape(3, 3)
    R_CO = np.dot(R_CB, R_OB.T)
    Rp = np.dot(R_CO, x[9:12])
    H = np.zeros((6, N))
    H[0:3, TH] = -R_CB
    H[3:6, TH] = np.dot(-skew(Rp), R_CB)
    H[3:6, P] = -R_CO
    H[:, TD] = np.dot(H[:, TH], w) + np.dot(H[:, P], v)
    return R_CO, Rp, H


_U = np.r_[np.arange(N)[BG], np.arange(N)[V]]  # the error-state entries of the rates the offset multiplies
_UU = np.ix_(_U, _U)
_W_DIAG = (np.arange(3), np.arange(3))
_B_COLUMNS = np.r_[np.arange(N)[TH], np.arange(N)[P]]
_B_SIGN = np.array([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])  # B = (-H_theta, H_p)


def offset_terms(H: np.ndarray, cov: np.ndarray, w_var: float, ratio: float = 3.0) -> tuple[np.ndarray, bool]:
    """What the first-order model leaves out between the time offset and the rates it multiplies, and
    whether the motion shows the offset at all.

    The pose at t + d_td moves by H_theta (w - d_w) d_td + H_p (v + d_v) d_td: beside H_td d_td, the
    products B u d_td with u = (d_w, d_v), B = (-H_theta, H_p), of covariance B (P_uu P_tt + P_ut P_tu)
    B^T (Gaussian errors; d_w is the bias's error plus one gyro sample's noise, variance `w_var`). That
    is added to the answer's covariance. And while H_td is not `ratio` times larger than the
    uncertainty of B u (a still device: w = v = 0), the offset is a consider state (Schmidt): in S, not
    corrected. Without either, an exact answer pulled the offset to whatever explained micrometres of
    noise through a velocity estimated at ~1 mm/s (20 ms off during a still start)."""
    B = H[:, _B_COLUMNS] * _B_SIGN
    P_uu = cov[_UU]
    P_uu[_W_DIAG] += w_var
    BPB = np.dot(np.dot(B, P_uu), B.T)
    b = np.dot(B, cov[_U, TD])
    extra = BPB * cov[TD, TD] + np.outer(b, b)
    h_td = H[:, TD]
    return extra, float(np.dot(h_td, h_td)) > ratio * ratio * float(BPB.trace())


def pose_covariance(H: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The 6x6 covariance of T_CO (wire convention) from the filter's covariance."""
    out = H @ cov @ H.T
    return 0.5 * (out + out.T)


def update(state: FilterState, td: float, T_CO_meas: np.ndarray, sigma: np.ndarray, R_CB: np.ndarray,
           t_CB: np.ndarray, w: tuple, w_var: float, gate_chi2: float, gravity_state: bool,
           offset_observable: bool = True) -> UpdateResult:
    """One ESKF update of `state` (the state at the measurement's time) with a backend T_CO; `w` the
    bias-corrected gyro rate there, `w_var` its sample noise's variance per axis; not `offset_observable`
    (in a gap of the IMU's stream, where the rate is the answers' own) the time offset is not corrected."""
    R_CO, Rp, H = pose_jacobian(state.x, R_CB, w, state.x[12:15])
    r = np.empty(6)
    r[0:3] = so3.log(T_CO_meas[:3, :3] @ R_CO.T)
    r[3:6] = T_CO_meas[:3, 3] - (t_CB - Rp)
    P0 = state.cov
    extra, excited = offset_terms(H, P0, w_var)
    sigma = sigma + extra
    # np.dot rather than @ throughout: ~0.3 us less per product, and this runs on every answer
    PHt = np.dot(P0, H.T)
    S = np.dot(H, PHt) + sigma
    S_inv = np.linalg.inv(0.5 * (S + S.T))
    chi2 = float(np.dot(r, np.dot(S_inv, r)))
    if not np.isfinite(chi2) or chi2 > gate_chi2:
        return UpdateResult(False, chi2, None, td, None, r, S)
    K = np.dot(PHt, S_inv)
    if not (excited and offset_observable):
        K[TD] = 0.0
    dx = np.dot(K, r)
    IKH = _I - np.dot(K, H)
    cov = np.dot(np.dot(IKH, P0), IKH.T) + np.dot(np.dot(K, sigma), K.T)
    cov = 0.5 * (cov + cov.T)
    x, c, td = inject(state.x, state.c, td, dx, gravity_state)
    return UpdateResult(True, chi2, FilterState(x, c, cov, None, state.held), td, IKH, r, S)
