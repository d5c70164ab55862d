"""PIM: the Pose Inspection Algorithm on the projected 3D bounding box."""

import numpy as np
import pytest

from client_sdk import Status
from client_sdk.inspection import PoseInspector, check_box
from flextrack.geometry import so3
from flextrack.geometry.camera import PinholeCamera, bbox_corners, project_model

CAM = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
BOX = bbox_corners(np.array([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]]))


def _uv(insp, R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return insp.project(T)


def test_area_of_a_cube_seen_face_on_is_its_front_face():
    insp = PoseInspector(CAM, BOX)
    uv = _uv(insp, np.eye(3), [0, 0, 1.0])
    # front face at z = 0.9 is 0.2 m wide: 500 * 0.2 / 0.9 px on a side; the back face lies inside it
    assert insp.area(uv) == pytest.approx((500 * 0.2 / 0.9) ** 2, rel=1e-12)


def test_area_is_the_image_bounding_box_of_the_projected_corners():
    rng = np.random.default_rng(3)
    insp = PoseInspector(CAM, BOX)
    for _ in range(20):
        R = so3.exp(rng.normal(size=3))
        t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.8, 1.5)])
        uv = _uv(insp, R, t)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        assert insp.area(uv) == pytest.approx((hi[0] - lo[0]) * (hi[1] - lo[1]), rel=1e-12)
    # a cube turned 45 deg about the optical axis: its face is a diamond, its image box the square around it
    uv = _uv(insp, so3.exp(np.array([0.0, 0.0, np.pi / 4])), [0, 0, 1.0])
    side = 500 * 0.2 / 0.9
    assert insp.area(uv) == pytest.approx(2 * side**2, rel=1e-9)


def test_projection_matches_the_shared_camera_model():
    insp = PoseInspector(CAM, BOX)
    R, t = so3.exp(np.array([0.2, -0.3, 0.1])), np.array([0.05, -0.02, 1.2])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    assert np.allclose(_uv(insp, R, t), project_model(CAM, T, BOX))


def test_statuses():
    insp = PoseInspector(CAM, BOX)
    near = _uv(insp, np.eye(3), [0, 0, 1.0])
    assert insp.inspect(near, None, 30.0)[0] is Status.FINE
    assert insp.inspect(near, near + 1.0, 30.0)[0] is Status.FINE
    # too small: area below 640 * 480 / 100 px^2 (the box at 20 m)
    far = _uv(insp, np.eye(3), [0, 0, 20.0])
    status, why = insp.inspect(far, None, 30.0)
    assert status is Status.TRACKING_LOST and "area" in why
    # behind the camera
    assert _uv(insp, np.eye(3), [0, 0, -1.0]) is None
    assert insp.inspect(None, near, 30.0)[0] is Status.TRACKING_LOST
    # partly behind (camera inside the box's depth range)
    assert _uv(insp, np.eye(3), [0, 0, 0.05]) is None


def test_wrong_pose_threshold_depends_on_the_frame_rate():
    insp = PoseInspector(CAM, BOX)
    assert insp.thr_2d(30.0) == 20.0 and insp.thr_2d(120.0) == 12.5
    uv = _uv(insp, np.eye(3), [0, 0, 1.0])
    jump = uv + np.array([15.0, 0.0])  # mean corner offset 15 px
    assert insp.inspect(jump, uv, 30.0)[0] is Status.FINE
    status, why = insp.inspect(jump, uv, 120.0)
    assert status is Status.WRONG_POSE and "15.0 px" in why
    assert insp.inspect(uv + np.array([12.5, 0.0]), uv, 120.0)[0] is Status.WRONG_POSE  # ">=" as the paper


def test_box_must_be_in_bbox_corners_order():
    check_box(BOX)
    tilted = BOX @ so3.exp(np.array([0.1, 0.2, 0.3])).T + 1.0  # an oriented box is fine
    check_box(tilted)
    with pytest.raises(ValueError, match="order"):
        check_box(BOX[[1, 0, 2, 3, 4, 5, 6, 7]])
    with pytest.raises(ValueError):
        check_box(BOX[:7])
    with pytest.raises(ValueError):
        check_box(np.full((8, 3), np.nan))
