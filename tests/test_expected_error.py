"""The mean 2D error a covariance predicts, against closed forms."""

import numpy as np
import pytest

from flextrack.evaluation.expected_error import expected_proj_px
from flextrack.geometry.camera import PinholeCamera

CAMERA = PinholeCamera.linemod()


def _pose(z: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


def test_a_sideways_translation_gives_the_half_normal_mean():
    sigma, z = 0.003, 0.8
    cov = np.zeros((1, 6, 6))
    cov[0, 3, 3] = sigma ** 2  # x only
    px = expected_proj_px(_pose(z)[None], cov, CAMERA, np.zeros((1, 3)), draws=40000,
                          rng=np.random.default_rng(1))
    assert px[0] == pytest.approx(CAMERA.fx * sigma / z * np.sqrt(2 / np.pi), rel=0.02)


def test_an_exact_covariance_predicts_no_error_and_depth_alone_moves_no_centred_point():
    cov = np.zeros((2, 6, 6))
    cov[1, 5, 5] = 0.01 ** 2  # along the optical axis: a point on it stays on it
    px = expected_proj_px(np.stack([_pose(1.0)] * 2), cov, CAMERA, np.zeros((1, 3)), draws=100)
    assert px == pytest.approx([0.0, 0.0], abs=1e-9)


def test_a_rotation_about_the_object_moves_points_off_its_centre_by_their_lever():
    sigma, z, lever = np.radians(0.5), 1.0, 0.05
    cov = np.zeros((1, 6, 6))
    cov[0, 2, 2] = sigma ** 2  # about the optical axis, through the object's origin
    px = expected_proj_px(_pose(z)[None], cov, CAMERA, np.array([[lever, 0.0, 0.0]]), draws=40000,
                          rng=np.random.default_rng(2))
    assert px[0] == pytest.approx(CAMERA.fy * lever * sigma / z * np.sqrt(2 / np.pi), rel=0.02)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="covariances"):
        expected_proj_px(_pose(1.0)[None], np.zeros((2, 6, 6)), CAMERA, np.zeros((1, 3)))
