"""PnP from 2D keypoints in the request against the object's registered 3D keypoints (OpenCV).

RANSAC (EPnP hypotheses) rejects outliers, Levenberg-Marquardt on the inliers refines; the lens
distortion of the request's intrinsics is part of the projection model. Confidence is the inlier
share times a Gaussian falloff of the inliers' RMS reprojection error.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.objects import ObjectRegistry
from flextrack.geometry import se3, so3

MIN_KEYPOINTS = 4


class PnpEstimator(Estimator):
    kind = "pnp"
    version = "1.0"
    description = "OpenCV PnP (RANSAC + LM refinement) from request keypoints to registered 3D keypoints"

    def __init__(self, objects: ObjectRegistry, name: str = "pnp", object_ids=(), ransac_px: float = 4.0,
                 iterations: int = 100, sigma_px: float = 2.0):
        super().__init__(name, list(object_ids) or objects.ids())
        self._registry = objects
        self.ransac_px = float(ransac_px)
        self.iterations = int(iterations)
        self.sigma_px = float(sigma_px)

    @classmethod
    def from_spec(cls, spec) -> PnpEstimator:
        spec.check_params({"ransac_px", "iterations", "sigma_px"})
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
        rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - points_2d[idx]) ** 2, axis=1))))
        T_CO = se3.make(so3.exp(rvec.ravel()), tvec.ravel())
        if T_CO[2, 3] <= 0:
            return EstimateOutput.not_found("pnp put the object behind the camera")
        confidence = len(idx) / len(points_3d) * float(np.exp(-0.5 * (rms / self.sigma_px) ** 2))
        return EstimateOutput(Status.OK, T_CO, confidence,
                              stage_ms={"pnp": (time.perf_counter() - start) * 1e3})
