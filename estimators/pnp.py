"""PnP from 2D keypoints in the request against the object's registered 3D keypoints (OpenCV).

RANSAC (EPnP hypotheses) rejects outliers, Levenberg-Marquardt on the inliers refines; the lens
distortion of the request's intrinsics is part of the projection model. Confidence is the inlier
share times a Gaussian falloff of the inliers' RMS reprojection error.

Covariance (wire convention, flextrack.wire): with the camera-frame inliers X_i = R X_O,i + t, the
true pose R_true = Exp(d_theta) R, t_true = t + d_t moves them by d_theta x (R X_O,i) + d_t, so the
2Nx6 Jacobian of the projections w.r.t. (d_theta, d_t) is, per point, D_i [-[R X_O,i]x, I], with D_i
= d(u, v)/dX (the pinhole's, with the lens distortion; OpenCV's d(u, v)/d tvec). Then

    Sigma = inflation * nu / (nu - 2) * s^2 (J^T J)^-1,   s^2 = max(uncut(sum r^2 / nu), floor_px^2),

over the N inliers, nu = 2N - 6 the residuals' degrees of freedom and s^2 the residual variance per
coordinate. `uncut` undoes RANSAC's cut: the inliers are the keypoints whose 2D residual is under
`ransac_px`, so at noise near the cut their residuals show only part of the noise (2 px noise, 4 px
cut: 69 %; mean NEES 8.3 without the correction, 5.6 with it; 1 px: 99.7 %, no change). nu / (nu - 2) makes it the covariance of the pose's Student-t posterior: s^2 from a few
residuals is itself uncertain (for 9 keypoints, nu = 12: a factor 1.2; nu is taken as at least 3,
so 4 keypoints get a factor 3). `floor_px` (0.3 px): keypoints are never located better than that,
and a perfect fit must not claim a pose known exactly. `inflation`: what the model leaves out
(linearisation), fitted by `flextrack evaluate nees` on its tuning set (docs/estimators.md; held-out
NEES over 0.5-2 px of keypoint noise there). e^T Sigma^-1 e is then 6 on average but not chi2(6): it has an F
distribution's longer tail (its median is lower, and 8-10 % of answers are above chi2(6)'s 95 %
quantile rather than 5 %).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.objects import ObjectRegistry
from flextrack.geometry import se3, so3

MIN_KEYPOINTS = 4
FLOOR_PX = 0.3  # the least keypoint noise a covariance assumes (per coordinate, px)
INFLATION = 1.0  # the covariance's calibration factor: `flextrack evaluate nees` fits 1.006 (docs/estimators.md)


def pose_jacobian(R: np.ndarray, t: np.ndarray, points_O: np.ndarray, K: np.ndarray,
                  dist: np.ndarray | None) -> np.ndarray:
    """(2N, 6) d(u, v) / d(d_theta, d_t) of the points' projections at pose (R, t), the perturbation in
    the wire convention (R_true = Exp(d_theta) R, t_true = t + d_t, camera frame)."""
    rvec, _ = cv2.Rodrigues(R)
    _, jac = cv2.projectPoints(points_O, rvec, t.reshape(3, 1), K, dist)
    D = jac[:, 3:6].reshape(-1, 2, 3)  # d(u, v)/d tvec = d(u, v)/dX, distortion included
    d_rot = -np.einsum("nij,njk->nik", D, so3.skew_batch(points_O @ R.T))
    return np.concatenate([d_rot, D], axis=2).reshape(-1, 6)


def kept_share_of_variance(a: float) -> float:
    """E[d^2 | d < c] / E[d^2] for a 2D Gaussian error of sigma per coordinate, a = c^2 / (2 sigma^2): the
    share of the variance the residuals RANSAC keeps (distance under c) still show (the truncated Rayleigh)."""
    if a > 50.0:
        return 1.0
    e = np.exp(-a)
    return float((1.0 - (1.0 + a) * e) / (1.0 - e))


# The most the correction multiplies the residual variance by: what it is at noise of half the cut (2 px at a
# 4 px cut), the range checked (docs/estimators.md). Noisier keypoints than that get a covariance too small.
CUT_CAP = 1.0 / kept_share_of_variance(2.0)


def uncut_variance(s2: float, cut_px: float | None) -> float:
    """The keypoint variance per coordinate behind residual variance `s2` measured on RANSAC's inliers, whose
    2D residuals are all under `cut_px`: at 2 px noise and a 4 px cut, 13.5 % of the good keypoints are cut and
    the kept ones show only 69 % of the variance. Solves s2 = sigma^2 * kept_share(cut^2 / (2 sigma^2)) by
    fixed-point iteration, capped at CUT_CAP times s2: a frame's s2 from 9 keypoints scatters by 40 %, and
    uncapped, the frames that happen to scatter towards cut^2 / 4 (which no finite sigma gives) would get
    covariances many times too large."""
    if cut_px is None or s2 <= 0:
        return s2
    sigma2 = s2
    for _ in range(100):
        new = min(s2 / kept_share_of_variance(cut_px ** 2 / (2.0 * sigma2)), CUT_CAP * s2)
        if abs(new - sigma2) <= 1e-9 * sigma2:
            break
        sigma2 = new
    return sigma2


def residual_variance(residuals: np.ndarray) -> tuple[float, int]:
    """(s^2, nu): the residual variance per coordinate of a fit of 6 parameters, and its degrees of freedom
    (nu = 2N - 6, at least 3)."""
    dof = max(residuals.size - 6, 3)
    return float(np.sum(residuals ** 2)) / dof, dof


def near_cut(residuals: np.ndarray, cut_px: float) -> bool:
    """Whether the residuals say the keypoint noise is above half the cut, where the correction stops
    (CUT_CAP) and the covariance may be too small."""
    s2, _ = residual_variance(residuals)
    return s2 > 0 and uncut_variance(s2, cut_px) >= CUT_CAP * s2 * (1 - 1e-6)


def information(J: np.ndarray, residuals: np.ndarray, floor_px: float, cut_px: float | None = None) -> np.ndarray:
    """(nu - 2) / nu * J^T J / s^2, s^2 the residual variance per coordinate (`residual_variance`), corrected
    for RANSAC's cut at `cut_px` (`uncut_variance`) and at least floor_px^2: the inverse of the pose
    covariance before inflation."""
    s2, dof = residual_variance(residuals)
    s2 = max(uncut_variance(s2, cut_px), floor_px ** 2)
    return (dof - 2) / dof * (J.T @ J) / s2


def covariance(info: np.ndarray, inflation: float = 1.0) -> np.ndarray:
    """inflation * info^-1, symmetrised."""
    cov = inflation * np.linalg.inv(info)
    return 0.5 * (cov + cov.T)


class PnpEstimator(Estimator):
    kind = "pnp"
    version = "1.0"
    description = "OpenCV PnP (RANSAC + LM refinement) from request keypoints to registered 3D keypoints"

    def __init__(self, objects: ObjectRegistry, name: str = "pnp", object_ids=(), ransac_px: float = 4.0,
                 iterations: int = 100, sigma_px: float = 2.0, floor_px: float = FLOOR_PX,
                 inflation: float = INFLATION):
        super().__init__(name, list(object_ids) or objects.ids())
        if not (floor_px > 0 and inflation > 0):
            raise ValueError(f"estimator '{name}': floor_px and inflation must be > 0")
        self._registry = objects
        self.ransac_px = float(ransac_px)
        self.iterations = int(iterations)
        self.sigma_px = float(sigma_px)
        self.floor_px = float(floor_px)
        self.inflation = float(inflation)

    @classmethod
    def from_spec(cls, spec) -> PnpEstimator:
        spec.check_params({"ransac_px", "iterations", "sigma_px", "floor_px", "inflation"})
        return cls(spec.objects, spec.name, spec.object_ids, **spec.params)

    def _correspondences(self, inp: EstimateInput, object_id: str) -> tuple[np.ndarray, np.ndarray]:
        keypoints_3d = self._registry.get(object_id).keypoints
        kp = np.asarray(inp.keypoints, dtype=float).reshape(-1, 3)
        if len(kp) < MIN_KEYPOINTS:
            raise InvalidInput(f"pnp needs at least {MIN_KEYPOINTS} keypoints, got {len(kp)}")
        ids = kp[:, 0].astype(int)
        bad = sorted({int(i) for i in ids if not 0 <= i < len(keypoints_3d)})
        if bad:
            raise InvalidInput(f"keypoint id(s) {bad} unknown for object '{object_id}' (ids 0..{len(keypoints_3d) - 1})")
        if len(set(ids.tolist())) != len(ids):
            raise InvalidInput("keypoint ids must be unique")
        return keypoints_3d[ids], kp[:, 1:3].copy()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        if inp.camera is None:
            raise InvalidInput("pnp needs the camera intrinsics (fx, fy, cx, cy, width, height)")
        object_id = self.resolve_object(inp.object_id)
        points_3d, points_2d = self._correspondences(inp, object_id)
        start = time.perf_counter()
        K = inp.camera.K
        dist = np.asarray(inp.camera.distortion, dtype=float) if inp.camera.distortion else None
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            points_3d, points_2d, K, dist, iterationsCount=self.iterations, reprojectionError=self.ransac_px,
            confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inliers is None or len(inliers) < MIN_KEYPOINTS:
            return EstimateOutput.not_found("pnp found no pose consistent with at least 4 keypoints")
        idx = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(points_3d[idx], points_2d[idx], K, dist, rvec, tvec)
        projected, _ = cv2.projectPoints(points_3d[idx], rvec, tvec, K, dist)
        residuals = projected.reshape(-1, 2) - points_2d[idx]
        rms = float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1))))
        T_CO = se3.make(so3.exp(rvec.ravel()), tvec.ravel())
        if T_CO[2, 3] <= 0:
            return EstimateOutput.not_found("pnp put the object behind the camera")
        J = pose_jacobian(T_CO[:3, :3], T_CO[:3, 3], points_3d[idx], K, dist)
        info = information(J, residuals, self.floor_px, self.ransac_px)
        try:
            degenerate = not np.all(np.isfinite(info)) or np.linalg.cond(info) > 1e12
        except np.linalg.LinAlgError:
            degenerate = True
        if degenerate:
            return EstimateOutput.not_found("pnp's keypoints do not fix the pose (degenerate layout)")
        confidence = len(idx) / len(points_3d) * float(np.exp(-0.5 * (rms / self.sigma_px) ** 2))
        message = (f"keypoint noise above half of ransac_px ({self.ransac_px:g} px), past the range where the "
                   "covariance is checked: it may be too small (raise ransac_px)"
                   if near_cut(residuals, self.ransac_px) else "")
        return EstimateOutput(Status.OK, T_CO, confidence, covariance=covariance(info, self.inflation),
                              message=message, stage_ms={"pnp": (time.perf_counter() - start) * 1e3})
