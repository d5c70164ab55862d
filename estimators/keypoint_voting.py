"""RANSAC voting for keypoints from a per-pixel unit-vector field (PVNet), vectorised in numpy.

Each object pixel p carries, per keypoint, a unit vector v pointing at it. Hypotheses are the
intersections of the rays of random pixel pairs; a pixel votes for a hypothesis h when the angle
between v and h - p is small (cosine above a threshold). The best-supported hypothesis is the
keypoint.

It is not refined by least squares over its inliers' rays (the point nearest to all of them): with
angular noise on the vectors that point is pulled towards the pixels, because a ray's distance to a
point grows with the point's distance from the ray's pixel. Keypoints off the object came out a
few per cent too close to the object's centre, which PnP reads as a few per cent more distance
(docs/pvnet.md); the vote count is an angular score and has no such pull.

`vote_with_spread` also gives each keypoint a 2x2 covariance, PVNet's: the scatter of its hypotheses
about their mean, each weighted by its votes (those with at least `spread_share` of the best's votes:
a far intersection of two nearly parallel rays would swamp the rest). It is a spread of single
pairs' intersections, a constant multiple of the keypoint's own error at best; the pose covariance
built on it is calibrated by one factor (estimators/pvnet.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VotingConfig:
    hypotheses: int = 64  # per keypoint
    cos_threshold: float = 0.99  # about 8 degrees
    max_pixels: int = 500  # pixels that score the hypotheses (a random subset beyond this)
    spread_share: float = 0.5  # hypotheses with at least this share of the best's votes make the spread


def _intersect(p1, v1, p2, v2):
    """Intersections of rays p1 + s v1 and p2 + t v2 (broadcast over leading axes); NaN when parallel."""
    cross = v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0]
    d = p2 - p1
    s = (d[..., 0] * v2[..., 1] - d[..., 1] * v2[..., 0]) / np.where(np.abs(cross) < 1e-3, np.nan, cross)
    return p1 + s[..., None] * v1


def _votes(h: np.ndarray, xy: np.ndarray, v: np.ndarray, cos_threshold: float) -> np.ndarray:
    """(K, H) counts of the pixels whose vector for keypoint k points at hypothesis h (K, H, 2) within the
    threshold; the pixels' coordinates xy (2, N) and vectors v (2, K, N) as contiguous rows (strided operands
    had doubled its cost). One keypoint at a time: the (K, H, N) arrays of all at once (MBs) went back to the
    system at each call and cost their page faults again at the next, most of the voting's time."""
    votes = np.empty(h.shape[:2], dtype=np.int64)
    for k in range(len(h)):
        dx = h[k, :, 0, None] - xy[0]  # (H, N)
        dy = h[k, :, 1, None] - xy[1]
        dot = dx * v[0, k] + dy * v[1, k]
        # (dot > 0) & (dot^2 > cos^2 |d|^2), in place
        dx *= dx
        dy *= dy
        dx += dy
        dx *= cos_threshold * cos_threshold
        inliers = dot > 0
        dot *= dot
        inliers &= dot > dx
        votes[k] = inliers.sum(axis=1)
    return votes


def vote(pixels: np.ndarray, vectors: np.ndarray, rng: np.random.Generator,
         config: VotingConfig = VotingConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (K, 2) and their inlier ratios (K,) from object pixels (N, 2) and unit vectors (N, K, 2)."""
    return vote_with_spread(pixels, vectors, rng, config)[:2]


def _spread(h: np.ndarray, score: np.ndarray, share: float) -> np.ndarray:
    """(K, 2, 2) vote-weighted covariances of the hypotheses h (K, H, 2) with votes score (K, H)."""
    w = np.where(score >= share * score.max(axis=1, keepdims=True), score, 0).astype(float)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    mean = np.einsum("kh,khi->ki", w, h)
    d = h - mean[:, None, :]
    return np.einsum("kh,khi,khj->kij", w, d, d)


def vote_with_spread(pixels: np.ndarray, vectors: np.ndarray, rng: np.random.Generator,
                     config: VotingConfig = VotingConfig()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`vote`, and per keypoint the (2, 2) covariance of its hypotheses (px^2; see the module's notes)."""
    n, k = vectors.shape[:2]
    if n < 2:
        raise ValueError(f"voting needs at least 2 pixels, got {n}")
    pixels = np.asarray(pixels, dtype=np.float64)
    vectors = np.asarray(vectors, dtype=np.float64)
    # (np.linalg.norm over the last axis, spelt out: numpy's reductions over short axes cost ~20 ns an element)
    vectors = vectors / (np.sqrt(vectors[..., 0] * vectors[..., 0] + vectors[..., 1] * vectors[..., 1]) + 1e-12)[..., None]
    sub = rng.choice(n, config.max_pixels, replace=False) if n > config.max_pixels else np.arange(n)
    i = rng.choice(sub, size=(k, config.hypotheses))
    j = rng.choice(sub, size=(k, config.hypotheses))
    kk = np.arange(k)[:, None]
    h = _intersect(pixels[i], vectors[i, kk], pixels[j], vectors[j, kk])  # (K, H, 2)
    h = np.where(np.isfinite(h), h, 1e9)  # parallel pairs: far away, no support
    score = _votes(h.astype(np.float32), np.ascontiguousarray(pixels[sub].T, dtype=np.float32),
                   np.ascontiguousarray(vectors[sub].transpose(2, 1, 0), dtype=np.float32), config.cos_threshold)
    kp = h[np.arange(k), np.argmax(score, axis=1)]
    support = _votes(kp[:, None, :], np.ascontiguousarray(pixels.T), np.ascontiguousarray(vectors.transpose(2, 1, 0)),
                     config.cos_threshold)[:, 0]  # (K,) of all n pixels
    return kp, support / n, _spread(h, score, config.spread_share)
