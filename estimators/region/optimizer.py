"""Regularised Newton steps on the pose from the correspondence lines, coarse to fine.

Pose increments follow flextrack.wire's convention: R <- Exp(d_theta) R, t <- t + d_t (camera
frame, rotation first). Each line is a Gaussian measurement of where its contour point should
project along its normal (mean mu, variance s2 from `contour_distributions`); its Jacobian is the
normal times the projection's derivative. The prior enters as a Tikhonov term weighted by the
inverse of its covariance (pulling towards the prior pose), and each step is damped towards the
current pose (SRT3D's per-step Tikhonov). The answer's covariance is that of the image's evidence
alone: the inverse of the lines' part of the final Hessian, divided by `covariance_inflation` (the
lines' errors are correlated, neighbouring lines see the same pixels, and the contour model is
approximate, the nearest of the sampled views, which a sum of independent terms overstates) times a
factor of the fit's colour agreement (`answer_covariance`: poorer agreement, larger errors than the
lines' spread says). The
prior is left out of it on purpose: the device that sent the prior holds it already, and a filter
that fused an answer with its own prior counted in would count that prior twice at every frame
(measured: its covariance halved with every answer and its NEES reached 1e6). Directions the
outline does not constrain (depth, often) are capped at `max_sigma_deg` / `max_sigma_m`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from estimators.region.correspondence import (
    PIXEL_CLIP,
    CellImage,
    LineModel,
    Lines,
    contour_distributions,
    edge_weighted,
    project_lines,
)
from estimators.region.histograms import ColourHistograms
from estimators.region.viewpoint_model import ViewpointModel
from flextrack.geometry import so3


@dataclass(frozen=True)
class OptimizerConfig:
    scales: tuple[int, ...] = (6, 4, 2, 1)  # segment sizes in px, coarse to fine
    iterations_per_scale: int = 2
    coarse_iterations: int = 1  # iterations at scales of 4 px and more (the first, rough steps)
    line_model: LineModel = field(default_factory=LineModel)
    line_weight: float = 1.0  # multiplies every line's information (1 / variance)
    damping_rotation: float = 10000.0  # per-step Tikhonov, per rad^2 (tuned on the real cat, docs/region.md)
    damping_translation: float = 300000.0  # per m^2
    covariance_inflation: float = 180.0  # fitted on the even frames of LM-O: mean NEES 6 at 10 mm / 5 deg (docs/region.md)
    # the inflation's factor by the answer's confidence (knots of a piecewise-linear curve, flat beyond the ends):
    # fitted on LM-O's even frames, where the mean NEES at a flat 350 fell from 11.7 at confidence 0.3-0.45 to 3.2 above
    # 0.75 (docs/results/region_lmo as stored at 69e45e2),
    # then scaled by 0.8 for a mean of 6 there with the fits' scatter (estimator._fits_scatter) added
    inflation_by_confidence: tuple[tuple[float, float], ...] = ((0.4, 1.05), (0.85, 0.45))
    max_sigma_deg: float = 45.0  # the covariance's cap where the outline says nothing
    max_sigma_m: float = 0.3


def line_jacobians(lines: Lines, K: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(6, M), a row a pose coordinate: d(projection along the normal) / d(d_theta, d_t)."""
    x, y, z = lines.points_C.T
    nu, nv = lines.normals.T
    J = np.empty((6, len(z)))
    a, b, c = J[3], J[4], J[5]
    np.multiply(nu, K[0, 0], out=a)
    a /= z
    np.multiply(nv, K[1, 1], out=b)
    b /= z
    np.multiply(a, x, out=c)
    c += b * y
    c /= -z
    # the rotated model point Q = P - t: dP/d_theta = -[Q]x, so n^T J_rot = Q x dP, dP = (a, b, c) = n^T d(uv)/dP
    qx, qy, qz = x - t[0], y - t[1], z - t[2]
    np.subtract(qy * c, qz * b, out=J[0])
    np.subtract(qz * a, qx * c, out=J[1])
    np.subtract(qx * b, qy * a, out=J[2])
    return J


def pose_error(R: np.ndarray, t: np.ndarray, R_ref: np.ndarray, t_ref: np.ndarray) -> np.ndarray:
    """(d_theta, d_t) with R = Exp(d_theta) R_ref, t = t_ref + d_t. (so3.log, not OpenCV's Rodrigues: that takes
    the angle from its cosine, off by up to 1e-8 rad, and calls one under 1e-5 rad none.)"""
    return np.concatenate([so3.log(R @ R_ref.T), t - t_ref])


@dataclass
class OptimizationResult:
    R: np.ndarray
    t: np.ndarray
    image_information: np.ndarray  # the lines' part of the final Hessian (the prior's left out)


def answer_covariance(result: OptimizationResult, cfg: OptimizerConfig, confidence: float) -> np.ndarray:
    """The answer's covariance: the image's evidence alone, inflated by `covariance_inflation` times the factor
    `inflation_by_confidence` gives at the fit's colour agreement; directions the outline does not constrain
    (depth, often) capped at `max_sigma_deg` / `max_sigma_m`."""
    knots = np.asarray(cfg.inflation_by_confidence, dtype=float)
    inflation = cfg.covariance_inflation * float(np.interp(confidence, knots[:, 0], knots[:, 1]))
    floor = np.diag([np.radians(cfg.max_sigma_deg) ** -2] * 3 + [cfg.max_sigma_m ** -2] * 3)
    covariance = np.linalg.inv(floor + result.image_information / inflation)
    return 0.5 * (covariance + covariance.T)


def optimize(frame: CellImage, K: np.ndarray, model: ViewpointModel, hist: ColourHistograms,
             R0: np.ndarray, t0: np.ndarray, prior_information: np.ndarray,
             cfg: OptimizerConfig, start: tuple[np.ndarray, np.ndarray] | None = None,
             scales: tuple[int, ...] | None = None, shape: tuple[int, int] = (480, 640)) -> OptimizationResult | None:
    """The pose refined from `start` (default: the prior's mean (R0, t0)) over `scales` (default: the
    config's); None when no lines fall in view."""
    R, t = (R0.copy(), t0.copy()) if start is None else (start[0].copy(), start[1].copy())
    damped = prior_information + np.diag([cfg.damping_rotation] * 3 + [cfg.damping_translation] * 3)
    logits = hist.logits(PIXEL_CLIP)
    H_image = np.zeros((6, 6))  # the image's information alone: the prior's is never subtracted back out
    for scale in scales or cfg.scales:
        for _ in range(cfg.coarse_iterations if scale >= 4 else cfg.iterations_per_scale):
            lines = project_lines(model, R, t, K, shape)
            if lines is None:
                return None
            mean, var, informative = contour_distributions(frame, logits, lines, scale, cfg.line_model)
            var = edge_weighted(frame, lines, mean, var, scale, cfg.line_model)
            J = line_jacobians(lines, K, t).compress(informative, axis=1)
            Jw = J * (cfg.line_weight / var.compress(informative))
            H_image = Jw @ J.T
            g = Jw @ mean.compress(informative) - prior_information @ pose_error(R, t, R0, t0)
            solved, step = cv2.solve(damped + H_image, g[:, None], flags=cv2.DECOMP_LU)  # LAPACK's dgesv's job
            if not solved:
                return None
            R = cv2.Rodrigues(step[:3])[0] @ R  # so3.exp's Rodrigues formula to 1e-16, at a fifth of the cost
            t = t + step[3:, 0]
    return OptimizationResult(R, t, H_image)
