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
