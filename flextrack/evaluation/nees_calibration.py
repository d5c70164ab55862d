"""`flextrack evaluate nees`: are the estimators' pose covariances calibrated?

For each answer with a pose, the NEES (normalised estimation error squared) is e^T Sigma^-1 e, with
e the true error of the pose in the wire convention (flextrack.wire.pose_error: rotation first, both
in the camera frame) and Sigma the covariance the estimator sent. For a calibrated, Gaussian
estimator it is chi-square with 6 degrees of freedom, and the mean of N answers is
Gamma(shape 3N, scale 2/N): its 95 % interval is the criterion (about [5.53, 6.51] for N = 200).
The median (5.35 for chi2(6)) and the share above chi2(6)'s 95 % quantile (12.59; 5 % expected)
show whether a mean is made by a few outliers.
"""

from __future__ import annotations

import numpy as np

CHI2_6_MEDIAN = 5.348  # scipy.stats.chi2.median(6)
CHI2_6_Q95 = 12.592  # scipy.stats.chi2.ppf(0.95, 6)


def nees(e: np.ndarray, covariance: np.ndarray) -> float:
    """e^T Sigma^-1 e of one answer (6-vectors in the wire convention)."""
    e = np.asarray(e, dtype=float)
    return float(e @ np.linalg.solve(covariance, e))


def mean_interval(n: int, level: float = 0.95) -> tuple[float, float]:
    """The `level` interval of the mean of n iid chi2(6) values: Gamma(shape 3n, scale 2/n)."""
    from scipy.stats import gamma

    lo, hi = gamma.ppf([(1 - level) / 2, (1 + level) / 2], a=3 * n, scale=2.0 / n)
    return float(lo), float(hi)


def summarise(values) -> dict:
    """N, mean, its 95 % interval, pass, median and share above 12.59 of a set of NEES values."""
    v = np.asarray(list(values), dtype=float)
    if not len(v):
        return {"n": 0, "mean": None, "interval": None, "median": None, "share_above_q95": None, "passed": False}
    lo, hi = mean_interval(len(v))
    mean = float(np.mean(v))
    return {"n": len(v), "mean": mean, "interval": [lo, hi], "median": float(np.median(v)),
            "share_above_q95": float(np.mean(v > CHI2_6_Q95)), "passed": bool(lo <= mean <= hi)}


def inflation_factor(values) -> float:
    """The one factor k by which covariances are scaled (Sigma -> k Sigma) to bring the mean NEES of
    these answers to 6, its expectation."""
    return float(np.mean(np.asarray(list(values), dtype=float)) / 6.0)


# ---- answers: (NEES, 2D error) per answer with a pose -------------------------------------------

def _default_object():
    from estimators.objects import load_object
    from flextrack.training.cli import DEFAULT_OBJECT

    return load_object("default", DEFAULT_OBJECT)


def pnp_answers(n: int, seed: int, noise_px: float = 1.0, outlier_share: float = 0.3, estimator=None,
                obj=None) -> list[dict]:
    """n PnP solves of the default object's registered keypoints projected at random poses (0.45-1.5 m,
    anywhere in a 640x480 view, seen from above), each coordinate with N(0, noise_px^2) noise; in a
    share `outlier_share` of the frames one keypoint is moved 15-60 px (RANSAC's to reject)."""
    from estimators.base import EstimateInput, Status
    from estimators.objects import ObjectRegistry
    from estimators.pnp import PnpEstimator
    from flextrack import wire
    from flextrack.geometry import se3
    from flextrack.geometry.camera import PinholeCamera
    from flextrack.training.pvnet_data import random_pose

    obj = obj or _default_object()
    estimator = estimator or PnpEstimator(ObjectRegistry([obj]))
    camera = PinholeCamera.linemod()
    centre = (obj.vertices.min(axis=0) + obj.vertices.max(axis=0)) / 2
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        T = random_pose(rng, camera, centre, (0.45, 1.5))
        uv = camera.project(se3.transform_points(T, obj.keypoints))
        noisy = uv + rng.normal(0.0, noise_px, uv.shape)
        if rng.uniform() < outlier_share:
            k = rng.integers(len(uv))
            angle = rng.uniform(0, 2 * np.pi)
            noisy[k] += rng.uniform(15, 60) * np.array([np.cos(angle), np.sin(angle)])
        kp = np.column_stack([np.arange(len(uv)), noisy])
        out = estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, keypoints=kp))
        if out.status is not Status.OK:
            continue
        e = wire.pose_error(out.T_CO, T)
        proj = float(np.mean(np.linalg.norm(camera.project(se3.transform_points(out.T_CO, obj.vertices))
                                            - camera.project(se3.transform_points(T, obj.vertices)), axis=1)))
        rows.append({"frame": i, "nees": nees(e, out.covariance), "proj_px": proj,
                     "std_deg": np.degrees(np.sqrt(np.diag(out.covariance)[:3])).tolist(),
                     "std_mm": (1e3 * np.sqrt(np.diag(out.covariance)[3:])).tolist()})
    return rows
