"""The mean 2D projection error a pose covariance predicts.

A covariance speaks in radians and metres; the criteria speak in pixels. Drawing poses from the
covariance (the wire convention, `flextrack.wire`) around the true pose and scoring them with the same
metric as the tracker's estimates turns a filter's own covariance, or a bound's, into the figure it
would be judged by: the expected `proj_px` of an estimator whose errors that covariance describes.
"""

from __future__ import annotations

import numpy as np

from flextrack.geometry import metrics, so3
from flextrack.geometry.camera import PinholeCamera


def expected_proj_px(T_true: np.ndarray, covariances: np.ndarray, camera: PinholeCamera, points_O: np.ndarray,
                     draws: int = 32, rng: np.random.Generator | None = None) -> np.ndarray:
    """Per frame (F,): the Monte-Carlo mean of `proj_px` over `draws` poses T_est whose wire error
    e = (d_theta, d_t) ~ N(0, covariance), i.e. R_est = Exp(-d_theta) R_true, t_est = t_true - d_t.

    `T_true` (F, 4, 4), `covariances` (F, 6, 6) symmetric positive semi-definite."""
    T_true = np.asarray(T_true, float)
    covariances = np.asarray(covariances, float)
    if T_true.shape[1:] != (4, 4) or covariances.shape != (len(T_true), 6, 6):
        raise ValueError(f"expected (F, 4, 4) poses and (F, 6, 6) covariances, got {T_true.shape} and "
                         f"{covariances.shape}")
    rng = rng or np.random.default_rng(0)
    # eigen-decomposition, not Cholesky: a covariance may be singular (an exact answer) and still be valid
    values, vectors = np.linalg.eigh(covariances)
    roots = vectors * np.sqrt(np.clip(values, 0.0, None))[:, None, :]
    errors = np.einsum("fij,fkj->fki", roots, rng.standard_normal((len(T_true), draws, 6)))  # (F, draws, 6)
    T_est = np.repeat(T_true[:, None], draws, axis=1).copy()
    R_err = so3.exp_many(-errors[..., :3].reshape(-1, 3)).reshape(len(T_true), draws, 3, 3)
    T_est[..., :3, :3] = R_err @ T_true[:, None, :3, :3]
    T_est[..., :3, 3] -= errors[..., 3:]
    flat_true = np.repeat(T_true, draws, axis=0)
    px = metrics.proj_px_many(T_est.reshape(-1, 4, 4), flat_true, camera, points_O)
    return px.reshape(len(T_true), draws).mean(axis=1)
