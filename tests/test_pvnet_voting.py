"""RANSAC keypoint voting and the training targets it inverts."""

import numpy as np
import pytest

from estimators.keypoint_voting import VotingConfig, vote
from flextrack.training.pvnet_data import targets


def _field(keypoints: np.ndarray, mask: np.ndarray):
    """Object pixels and exact unit vectors at the output grid of the training targets."""
    m, vec = targets(mask[None], keypoints[None].astype(np.float32))
    rows, cols = np.nonzero(m[0])
    k = len(keypoints)
    vectors = vec[0].reshape(k, 2, *m.shape[1:])[:, :, rows, cols].transpose(2, 0, 1)
    return np.stack([2 * cols + 0.5, 2 * rows + 0.5], axis=1), vectors


def test_exact_field_gives_the_keypoints_within_half_a_pixel():
    rng = np.random.default_rng(3)
    mask = np.zeros((128, 128), np.uint8)
    mask[40:90, 30:100] = 1
    keypoints = rng.uniform(10, 118, size=(9, 2))  # inside and outside the mask
    pixels, vectors = _field(keypoints, mask)
    found, inlier_ratio = vote(pixels, vectors, np.random.default_rng(0))
    assert np.max(np.linalg.norm(found - keypoints, axis=1)) < 0.5
    assert np.all(inlier_ratio > 0.99)


def test_outliers_and_noise_are_voted_down():
    rng = np.random.default_rng(4)
    mask = np.zeros((128, 128), np.uint8)
    mask[30:100, 30:100] = 1
    keypoints = rng.uniform(30, 100, size=(9, 2))
    pixels, vectors = _field(keypoints, mask)
    angle = rng.normal(0, np.radians(2), size=vectors.shape[:2])
    c, s = np.cos(angle), np.sin(angle)
    vectors = np.stack([c * vectors[..., 0] - s * vectors[..., 1], s * vectors[..., 0] + c * vectors[..., 1]], -1)
    bad = rng.random(len(pixels)) < 0.3  # 30 % of the pixels point anywhere
    vectors[bad] = rng.normal(size=(bad.sum(), 9, 2))
    found, inlier_ratio = vote(pixels, vectors, np.random.default_rng(0), VotingConfig())
    assert np.max(np.linalg.norm(found - keypoints, axis=1)) < 1.5
    assert np.all((inlier_ratio > 0.5) & (inlier_ratio < 0.8))


def test_too_few_pixels_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 2 pixels"):
        vote(np.zeros((1, 2)), np.ones((1, 9, 2)), np.random.default_rng(0))


def test_keypoints_off_the_object_are_not_pulled_towards_it():
    """With angular noise, the point nearest to the inlier rays lies closer to the pixels than the keypoint
    (distance to a ray grows with distance from its pixel); the vote is angular and stays centred on it."""
    mask = np.zeros((128, 128), np.uint8)
    mask[34:94, 34:94] = 1  # a 60 px object, as the crop pass sees it
    angles = np.linspace(0, 2 * np.pi, 9, endpoint=False)
    keypoints = 64 + 40 * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # just off its sides
    pixels, exact = _field(keypoints, mask)
    radial = []
    for seed in range(5):
        noise = np.random.default_rng(seed).normal(0, np.radians(6), size=exact.shape[:2])
        c, s = np.cos(noise), np.sin(noise)
        vectors = np.stack([c * exact[..., 0] - s * exact[..., 1], s * exact[..., 0] + c * exact[..., 1]], -1)
        found = vote(pixels, vectors, np.random.default_rng(seed))[0]
        radial.append(np.linalg.norm(found - 64, axis=1) - 40)
    assert abs(np.mean(radial)) < 0.6  # px over 45 keypoints; the least-squares refinement gave -1.5
