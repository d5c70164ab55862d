"""PnP from 2D keypoints in the request against the object's registered 3D keypoints (OpenCV).

RANSAC (EPnP hypotheses) rejects outliers, Levenberg-Marquardt on the inliers refines; the lens
distortion of the request's intrinsics is part of the projection model. Confidence is the inlier
share times a Gaussian falloff of the inliers' RMS reprojection error.

Covariance (wire convention, flextrack.wire): with the camera-frame inliers X_i = R X_O,i + t, the
true pose R_true = Exp(d_theta) R, t_true = t + d_t moves them by d_theta x (R X_O,i) + d_t, so the
2Nx6 Jacobian of the projections w.r.t. (d_theta, d_t) is, per point, D_i [-[R X_O,i]x, I], with D_i
= d(u, v)/dX (the pinhole's, with the lens distortion; OpenCV's d(u, v)/d tvec). Then

    Sigma = inflation * nu / (nu - 2) * s^2 (J^T J)^-1,   s^2 = max(sum r^2 / nu, floor_px^2),

over the N inliers, nu = 2N - 6 the residuals' degrees of freedom and s^2 the residual variance per
coordinate. nu / (nu - 2) makes it the covariance of the pose's Student-t posterior: s^2 from a few
residuals is itself uncertain (for 9 keypoints, nu = 12: a factor 1.2; nu is taken as at least 3,
so 4 keypoints get a factor 3). `floor_px` (0.3 px): keypoints are never located better than that,
and a perfect fit must not claim a pose known exactly. `inflation`: what the model leaves out
(RANSAC's cut of the residuals, linearisation), fitted by `flextrack evaluate nees` on its tuning
set (docs/estimators.md). e^T Sigma^-1 e is then 6 on average but not chi2(6): it has an F
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


def information(J: np.ndarray, residuals: np.ndarray, floor_px: float) -> np.ndarray:
    """(nu - 2) / nu * J^T J / s^2, s^2 the residual variance per coordinate (nu = 2N - 6 degrees of
    freedom, at least 3) and at least floor_px^2: the inverse of the pose covariance before inflation."""
    dof = max(residuals.size - 6, 3)
    s2 = max(float(np.sum(residuals ** 2)) / dof, floor_px ** 2)
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
        info = information(J, residuals, self.floor_px)
        try:
            degenerate = not np.all(np.isfinite(info)) or np.linalg.cond(info) > 1e12
        except np.linalg.LinAlgError:
            degenerate = True
        if degenerate:
            return EstimateOutput.not_found("pnp's keypoints do not fix the pose (degenerate layout)")
        confidence = len(idx) / len(points_3d) * float(np.exp(-0.5 * (rms / self.sigma_px) ** 2))
        return EstimateOutput(Status.OK, T_CO, confidence, covariance=covariance(info, self.inflation),
                              stage_ms={"pnp": (time.perf_counter() - start) * 1e3})
