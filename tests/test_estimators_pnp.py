"""pnp: a known pose back from noise-free keypoints, with and without distortion; outliers; bad input."""

import cv2
import numpy as np
import pytest
import trimesh

from estimators.base import EstimateInput, InvalidInput, Status, UnknownObject
from estimators.objects import ObjectRegistry, load_object
from estimators.pnp import PnpEstimator
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    path = tmp_path_factory.mktemp("obj") / "obj_000001.ply"
    trimesh.creation.icosphere(subdivisions=2, radius=50.0).apply_scale((1.0, 0.7, 0.5)).export(path)
    return ObjectRegistry([load_object("ellipsoid", path)])


T_TRUE = se3.make(so3.exp(np.array([0.4, -0.9, 0.25])), np.array([0.03, -0.02, 0.55]))


def keypoints(objects, camera, T=T_TRUE):
    points = objects.get("ellipsoid").keypoints
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    dist = np.asarray(camera.distortion) if camera.distortion else None
    uv, _ = cv2.projectPoints(points, rvec, T[:3, 3], camera.K, dist)
    return np.column_stack([np.arange(len(points)), uv.reshape(-1, 2)])


@pytest.mark.parametrize("distortion", [(), (0.12, -0.25, 0.001, -0.002, 0.05)])
def test_known_pose_comes_back_within_0_05_deg_and_0_5_mm(objects, distortion):
    camera = PinholeCamera(572.4, 573.6, 325.3, 242.0, 640, 480, distortion)
    out = PnpEstimator(objects).estimate(EstimateInput(1, 0, "ellipsoid", camera=camera,
                                                       keypoints=keypoints(objects, camera)))
    assert out.status is Status.OK
    assert metrics.re_deg(out.T_CO, T_TRUE) < 0.05 and metrics.te_mm(out.T_CO, T_TRUE) < 0.5
    assert out.confidence > 0.99 and "pnp" in out.stage_ms


def test_ransac_rejects_an_outlier_and_confidence_drops(objects):
    camera = PinholeCamera.linemod()
    kp = keypoints(objects, camera)
    kp[2, 1:] += (80.0, -60.0)
    out = PnpEstimator(objects).estimate(EstimateInput(1, 0, camera=camera, keypoints=kp))
    assert out.status is Status.OK and metrics.re_deg(out.T_CO, T_TRUE) < 0.05
    assert out.confidence == pytest.approx(8 / 9, abs=0.01)


def test_bad_input_raises_invalid_input(objects):
    pnp = PnpEstimator(objects)
    camera = PinholeCamera.linemod()
    kp = keypoints(objects, camera)
    with pytest.raises(InvalidInput, match="at least 4"):
        pnp.estimate(EstimateInput(1, 0, camera=camera, keypoints=kp[:3]))
    bad_id = kp.copy()
    bad_id[0, 0] = 42
    with pytest.raises(InvalidInput, match="42"):
        pnp.estimate(EstimateInput(1, 0, camera=camera, keypoints=bad_id))
    with pytest.raises(InvalidInput, match="unique"):
        pnp.estimate(EstimateInput(1, 0, camera=camera, keypoints=np.vstack([kp, kp[:1]])))
    with pytest.raises(InvalidInput, match="intrinsics"):
        pnp.estimate(EstimateInput(1, 0, keypoints=kp))
    with pytest.raises(UnknownObject, match="cup"):
        pnp.estimate(EstimateInput(1, 0, "cup", camera=camera, keypoints=kp))


def test_the_cut_correction_recovers_the_noise_behind_ransacs_inliers():
    """Residuals of 2 px per coordinate cut at 4 px (RANSAC's threshold on the 2D distance): the kept ones show
    about 69 % of the variance; `uncut_variance` gives the 2 px back. Far from the cut nothing changes; past
    half the cut the correction stops at CUT_CAP."""
    from estimators.pnp import CUT_CAP, kept_share_of_variance, uncut_variance

    rng = np.random.default_rng(0)
    for sigma, cut in ((2.0, 4.0), (1.0, 4.0), (1.5, 4.0)):  # up to half the cut: past it the cap holds
        d = rng.normal(scale=sigma, size=(400_000, 2))
        kept = d[np.hypot(d[:, 0], d[:, 1]) < cut]
        s2 = float(np.mean(kept ** 2))  # per coordinate, what the inliers show
        assert s2 / sigma ** 2 == pytest.approx(kept_share_of_variance(cut ** 2 / (2 * sigma ** 2)), rel=0.01)
        assert uncut_variance(s2, cut) == pytest.approx(sigma ** 2, rel=0.02)
    assert kept_share_of_variance(2.0) == pytest.approx(0.687, abs=1e-3)
    assert uncut_variance(0.5, 40.0) == pytest.approx(0.5, rel=1e-9) and uncut_variance(0.5, None) == 0.5
    assert CUT_CAP == pytest.approx(1 / 0.687, abs=1e-2)  # the correction at noise of half the cut
    assert uncut_variance(3.5, 4.0) == CUT_CAP * 3.5  # near the whole cut's spread: capped, not unbounded


def test_an_answer_from_keypoints_noisier_than_half_the_cut_says_its_covariance_may_be_too_small(objects):
    camera = PinholeCamera.linemod()
    kp = keypoints(objects, camera)
    rng = np.random.default_rng(4)
    messages = {}
    for noise in (0.3, 3.0):
        est = PnpEstimator(objects, ransac_px=4.0)
        noisy = kp.copy()
        noisy[:, 1:] += rng.normal(scale=noise, size=(len(kp), 2))
        out = est.estimate(EstimateInput(frame_id=0, capture_time_ns=0, camera=camera, keypoints=noisy))
        messages[noise] = out.message if out.status == Status.OK else "not found"
    assert messages[0.3] == "" and "ransac_px" in messages[3.0]
