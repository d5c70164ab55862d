"""The one geometry and metrics implementation, cross-checked against independent references:
scipy's Rotation for SO(3) (exp, log, quaternions in both orders, slerp) and the BOP toolkit's
definitions of the pose errors (bop_toolkit_lib/pose_error.py: re, te, proj, add, adi), written
out here as the toolkit writes them, on random poses over the whole rotation range.
"""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera

RNG = np.random.default_rng(20261124)
ROTVECS = np.concatenate([
    Rotation.random(200, random_state=1).as_rotvec(),  # uniform over SO(3)
    RNG.normal(size=(20, 3)) * 1e-9,  # near the identity (the small-angle branches)
    [v / np.linalg.norm(v) * (np.pi - 1e-7) for v in RNG.normal(size=(20, 3))],  # near pi
    [[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [0, 0, 0]],
])


@pytest.mark.parametrize("phi", ROTVECS, ids=lambda v: f"{np.linalg.norm(v):.3g}rad")
def test_exp_and_log_match_scipy(phi):
    R = so3.exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    # log: the same rotation (a rotation vector of angle pi and its negation are the same rotation)
    back = so3.log(R)
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), R, atol=1e-9)
    assert np.linalg.norm(back) <= np.pi + 1e-9
    if np.linalg.norm(phi) < np.pi - 1e-6:
        np.testing.assert_allclose(back, Rotation.from_matrix(R).as_rotvec(), atol=1e-9)


@pytest.mark.parametrize("phi", ROTVECS[::7], ids=lambda v: f"{np.linalg.norm(v):.3g}rad")
def test_quaternions_match_scipy_in_both_orders(phi):
    R = Rotation.from_rotvec(phi)
    xyzw = R.as_quat()  # scipy: x y z w (TUM's order); ours: w x y z (EuRoC's and the wire's)
    q = so3.quat_from_matrix(R.as_matrix())
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    expected = np.roll(xyzw, 1) * (1 if xyzw[3] >= 0 else -1)
    if abs(q[0]) > 1e-9:  # at w = 0, q and -q both have w >= 0
        np.testing.assert_allclose(q, expected, atol=1e-12)
    np.testing.assert_allclose(so3.matrix_from_quat(np.roll(xyzw, 1)), R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(so3.matrix_from_quat(3.0 * np.roll(xyzw, 1)), R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(Rotation.from_rotvec(so3.rotvec_from_quat(q)).as_matrix(), R.as_matrix(), atol=1e-9)
    T = se3.from_quat_translation(q, np.array([0.1, -0.2, 1.2]))
    q2, t2 = se3.to_quat_translation(T)
    np.testing.assert_allclose(t2, [0.1, -0.2, 1.2])
    np.testing.assert_allclose(T[:3, :3], R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(abs(np.dot(q2, q)), 1.0, atol=1e-12)


def test_slerp_matches_scipy():
    for a, b in Rotation.random(20, random_state=3).as_quat().reshape(10, 2, 4):
        key = Rotation.from_quat([a, b])
        for s in (0.0, 0.25, 0.5, 0.9, 1.0):
            ours = so3.matrix_from_quat(so3.slerp(np.roll(a, 1), np.roll(b, 1), s))
            np.testing.assert_allclose(ours, Slerp([0, 1], key)([s]).as_matrix()[0], atol=1e-9)


# -- the BOP toolkit's definitions (bop_toolkit_lib/pose_error.py, misc.py), as written there ----------------

def _bop_transform_pts_Rt(pts, R, t):
    return (R.dot(pts.T) + t.reshape((3, 1))).T


def _bop_project_pts(pts, K, R, t):
    P = K.dot(np.hstack((R, t.reshape(3, 1))))
    pts_im = P.dot(np.hstack((pts, np.ones((pts.shape[0], 1)))).T)
    pts_im /= pts_im[2, :]
    return pts_im[:2, :].T


def _bop_re(R_est, R_gt):
    error_cos = float(0.5 * (np.trace(R_est.dot(np.linalg.inv(R_gt))) - 1.0))
    error_cos = min(1.0, max(-1.0, error_cos))
    return 180.0 * math.acos(error_cos) / np.pi


def _bop_te(t_est, t_gt):
    return np.linalg.norm(t_gt - t_est)


def _bop_add(R_est, t_est, R_gt, t_gt, pts):
    return np.linalg.norm(_bop_transform_pts_Rt(pts, R_est, t_est) - _bop_transform_pts_Rt(pts, R_gt, t_gt),
                          axis=1).mean()


def _bop_adi(R_est, t_est, R_gt, t_gt, pts):
    nn_dists, _ = cKDTree(_bop_transform_pts_Rt(pts, R_est, t_est)).query(_bop_transform_pts_Rt(pts, R_gt, t_gt), k=1)
    return nn_dists.mean()


def _bop_proj(R_est, t_est, R_gt, t_gt, K, pts):
    return np.linalg.norm(_bop_project_pts(pts, K, R_est, t_est) - _bop_project_pts(pts, K, R_gt, t_gt), axis=1).mean()


def _pose_pairs(n=30):
    rng = np.random.default_rng(7)
    for R_gt, dR in zip(Rotation.random(n, random_state=5), Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.3)):
        t_gt = np.array([0.0, 0.0, 1.2]) + rng.normal(size=3) * 0.1
        T_gt = se3.make(R_gt.as_matrix(), t_gt)
        T_est = se3.make((dR * R_gt).as_matrix(), t_gt + rng.normal(size=3) * 0.01)
        yield T_est, T_gt


def test_metrics_match_the_bop_toolkit_definitions():
    pts = np.random.default_rng(11).uniform(-0.05, 0.05, size=(500, 3))  # an object ~10 cm across, metres
    camera = PinholeCamera(572.4, 573.6, 325.3, 242.0, 640, 480)
    for T_est, T_gt in _pose_pairs():
        R_est, t_est, R_gt, t_gt = T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3]
        assert metrics.re_deg(T_est, T_gt) == pytest.approx(_bop_re(R_est, R_gt), abs=1e-6)
        assert metrics.te_mm(T_est, T_gt) == pytest.approx(1000 * _bop_te(t_est, t_gt), rel=1e-12)
        assert metrics.add_m(T_est, T_gt, pts) == pytest.approx(_bop_add(R_est, t_est, R_gt, t_gt, pts), rel=1e-12)
        assert metrics.adds_m(T_est, T_gt, pts) == pytest.approx(_bop_adi(R_est, t_est, R_gt, t_gt, pts), rel=1e-9)
        assert metrics.proj_px(T_est, T_gt, camera, pts) == pytest.approx(
            _bop_proj(R_est, t_est, R_gt, t_gt, camera.K, pts), rel=1e-9)
    T_est, T_gt = np.stack([p[0] for p in _pose_pairs()]), np.stack([p[1] for p in _pose_pairs()])
    many = metrics.proj_px_many(T_est, T_gt, camera, pts)
    np.testing.assert_allclose(many, [_bop_proj(e[:3, :3], e[:3, 3], g[:3, :3], g[:3, 3], camera.K, pts)
                                      for e, g in zip(T_est, T_gt)], rtol=1e-9)


def test_wire_conversions_round_trip_and_keep_the_distortion():
    from flextrack import wire

    camera = PinholeCamera(572.4, 573.6, 325.3, 242.0, 640, 480, (0.1, -0.05, 0.001, 0.002, 0.0))
    msg = wire.intrinsics_to_pb(camera)
    assert (msg.fx, msg.fy, msg.cx, msg.cy, msg.width, msg.height) == (572.4, 573.6, 325.3, 242.0, 640, 480)
    assert list(msg.distortion) == pytest.approx(camera.distortion)
    for T, _ in _pose_pairs(5):
        np.testing.assert_allclose(wire.pose_from_pb(wire.pose_to_pb(T)), T, atol=1e-12)
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    np.testing.assert_array_equal(wire.covariance_from_pb(wire.covariance_to_pb(cov)), cov)


def test_exp_many_is_exp_row_by_row():
    phi = np.concatenate([ROTVECS, -ROTVECS[:50]])
    many = so3.exp_many(phi)
    np.testing.assert_allclose(many, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(many, np.stack([so3.exp(v) for v in phi]), atol=1e-14)


def test_look_at_puts_the_target_on_the_axis_with_up_at_the_top_of_the_image():
    from flextrack.geometry.camera import look_at

    camera = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    rng = np.random.default_rng(3)
    for _ in range(20):
        eye, target = rng.normal(size=3), rng.normal(size=3) * 0.1
        R_CW = look_at(eye, target)
        assert np.allclose(R_CW @ R_CW.T, np.eye(3)) and np.isclose(np.linalg.det(R_CW), 1.0)
        T_CW = se3.make(R_CW, -R_CW @ eye)
        uv = camera.project(se3.transform_points(T_CW, np.stack([target, target + [0, 0, 0.01]])))
        np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
        assert uv[1, 1] < uv[0, 1]  # world up is up in the image (OpenCV y down)
