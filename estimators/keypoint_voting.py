"""RANSAC voting for keypoints from a per-pixel unit-vector field (PVNet), vectorised in numpy.

Each object pixel p carries, per keypoint, a unit vector v pointing at it. Hypotheses are the
intersections of the rays of random pixel pairs; a pixel votes for a hypothesis h when the angle
between v and h - p is small (cosine above a threshold). The best-supported hypothesis is refined
by least squares over its inliers' rays (the point nearest to all of them), twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VotingConfig:
    hypotheses: int = 64  # per keypoint
    cos_threshold: float = 0.99  # about 8 degrees
    max_pixels: int = 500  # pixels that score the hypotheses (a random subset beyond this)
    refine_iterations: int = 2


def _intersect(p1, v1, p2, v2):
    """Intersections of rays p1 + s v1 and p2 + t v2 (broadcast over leading axes); NaN when parallel."""
    cross = v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0]
    d = p2 - p1
    s = (d[..., 0] * v2[..., 1] - d[..., 1] * v2[..., 0]) / np.where(np.abs(cross) < 1e-3, np.nan, cross)
    return p1 + s[..., None] * v1


def _inliers(h: np.ndarray, pixels: np.ndarray, vectors: np.ndarray, cos_threshold: float) -> np.ndarray:
    """(K, H, N) bool: pixel n's vector for keypoint k points at hypothesis h within the threshold."""
    dx = h[:, :, None, 0] - pixels[None, None, :, 0]  # (K, H, N)
    dy = h[:, :, None, 1] - pixels[None, None, :, 1]
    dot = dx * vectors.T[0][:, None, :] + dy * vectors.T[1][:, None, :]
    return (dot > 0) & (dot * dot > (cos_threshold * cos_threshold) * (dx * dx + dy * dy))


def _least_squares_point(pixels: np.ndarray, vectors: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K, 2): per keypoint, the point minimising the weighted squared distances to the rays.

    Normal equations sum_n w (I - v v^T) x = sum_n w (I - v v^T) p, written out for 2x2.
    """
    vx, vy = vectors[..., 0], vectors[..., 1]  # (N, K)
    px, py = pixels[:, 0:1], pixels[:, 1:2]
    a, b, c = weights * (1 - vx * vx), -weights * vx * vy, weights * (1 - vy * vy)
    A = np.stack([np.stack([a.sum(0), b.sum(0)], -1), np.stack([b.sum(0), c.sum(0)], -1)], -2)  # (K, 2, 2)
    rhs = np.stack([(a * px + b * py).sum(0), (b * px + c * py).sum(0)], -1)  # (K, 2)
    return np.linalg.solve(A + 1e-9 * np.eye(2), rhs[..., None])[..., 0]


def vote(pixels: np.ndarray, vectors: np.ndarray, rng: np.random.Generator,
         config: VotingConfig = VotingConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (K, 2) and their inlier ratios (K,) from object pixels (N, 2) and unit vectors (N, K, 2)."""
    n, k = vectors.shape[:2]
    if n < 2:
        raise ValueError(f"voting needs at least 2 pixels, got {n}")
    pixels = np.asarray(pixels, dtype=np.float64)
    vectors = np.asarray(vectors, dtype=np.float64)
    vectors = vectors / (np.linalg.norm(vectors, axis=2, keepdims=True) + 1e-12)
    sub = rng.choice(n, config.max_pixels, replace=False) if n > config.max_pixels else np.arange(n)
    i = rng.choice(sub, size=(k, config.hypotheses))
    j = rng.choice(sub, size=(k, config.hypotheses))
    kk = np.arange(k)[:, None]
    h = _intersect(pixels[i], vectors[i, kk], pixels[j], vectors[j, kk])  # (K, H, 2)
    h = np.where(np.isfinite(h), h, 1e9)  # parallel pairs: far away, no support
    score = _inliers(h.astype(np.float32), pixels[sub].astype(np.float32), vectors[sub].astype(np.float32),
                     config.cos_threshold).sum(axis=2)
    kp = h[np.arange(k), np.argmax(score, axis=1)]
    support = _inliers(kp[:, None, :], pixels, vectors, config.cos_threshold)[:, 0].T.astype(np.float64)  # (N, K)
    for _ in range(config.refine_iterations):
        if np.any(support.sum(axis=0) < 2):
            break
        kp = _least_squares_point(pixels, vectors, support)
        support = _inliers(kp[:, None, :], pixels, vectors, config.cos_threshold)[:, 0].T.astype(np.float64)
    return kp, support.mean(axis=0)
