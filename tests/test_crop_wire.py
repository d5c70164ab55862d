"""Crops of the frame on the wire, through a real gRPC server on loopback: a crop gives the pose the
whole frame gives (region on a rendered frame, pnp on keypoints in full-frame pixels), a bad crop is
refused with INVALID_ARGUMENT saying why, and the SDK crops to the prior's box grown by its
uncertainty, sending the whole frame when it has nothing to crop to."""

import cv2
import grpc
import numpy as np
import pytest

from client_sdk.crop import CropOptions, crop_rect, projection_std_px, request_crop
from client_sdk.refinement import RefinementRequest
from client_sdk.transport import make_request
from estimators.objects import ObjectRegistry
from estimators.pnp import PnpEstimator
from estimators.registry import EstimatorRegistry
from flextrack import wire
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera, bbox_corners
from flextrack.testing.region_scene import rendered_region_scene
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.server import BackgroundServer

CAMERA = PinholeCamera.linemod()
PRIOR_COV = wire.diagonal_covariance(np.radians(2), 0.004)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    region, obj, T, rgb = rendered_region_scene(tmp_path_factory.mktemp("region_cache"), CAMERA)
    registry = EstimatorRegistry([region, PnpEstimator(ObjectRegistry([obj]), object_ids=["default"])],
                                 objects=ObjectRegistry([obj]))
    with BackgroundServer(registry) as server, grpc.insecure_channel(server.address) as channel:
        yield pb_grpc.PoseEstimationStub(channel), rgb, T, obj


def png(rgb):
    return cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))[1].tobytes()


def request(rgb, crop=None, keypoints=(), **kw):
    """The frame (or its crop) as the SDK sends it."""
    if crop is not None and crop.width and crop.height:
        rgb = rgb[crop.y:crop.y + crop.height, crop.x:crop.x + crop.width]
    req = make_request(frame_id=1, capture_time_ns=0, object_id="default", image=png(rgb), encoding=pb.Image.PNG,
                       width=rgb.shape[1], height=rgb.shape[0], intrinsics=wire.intrinsics_to_pb(CAMERA),
                       crop=crop, **kw)
    req.keypoints.extend(keypoints)
    return req


def test_a_crop_gives_region_the_pose_the_whole_frame_gives(world):
    stub, rgb, T, obj = world
    T_prior = se3.make(so3.exp(np.radians([1.5, -1.0, 1.0])) @ T[:3, :3], T[:3, 3] + [0.003, -0.002, 0.004])
    prior = pb.PosePrior(pose=wire.pose_to_pb(T_prior), covariance=wire.covariance_to_pb(PRIOR_COV))
    x, y, w, h = crop_rect(CAMERA, bbox_corners(obj.vertices), T_prior, PRIOR_COV)
    assert w * h < 0.3 * CAMERA.width * CAMERA.height  # a real cut, not the frame
    crop = pb.Crop(x=x, y=y, width=w, height=h)
    whole = stub.Estimate(request(rgb, estimator="region", session_id="whole", prior=prior))
    cut = stub.Estimate(request(rgb, crop, estimator="region", session_id="cut", prior=prior))
    assert whole.status == cut.status == pb.EstimateResponse.OK, (whole.message, cut.message)
    T_whole, T_cut = wire.pose_from_pb(whole.pose), wire.pose_from_pb(cut.pose)
    assert metrics.proj_px(T_whole, T, CAMERA, obj.vertices) < 1.0
    assert metrics.proj_px(T_cut, T_whole, CAMERA, obj.vertices) < 0.05  # the same pose, in the camera frame


def test_a_crop_leaves_keypoints_in_full_frame_pixels(world):
    stub, rgb, T, obj = world
    uv = CAMERA.project(obj.keypoints @ T[:3, :3].T + T[:3, 3])
    keypoints = [pb.Keypoint(id=i, u=u, v=v) for i, (u, v) in enumerate(uv)]
    crop = pb.Crop(x=96, y=64, width=320, height=256)
    for c in (None, crop):
        answer = stub.Estimate(request(rgb, c, estimator="pnp", keypoints=keypoints))
        assert answer.status == pb.EstimateResponse.OK, answer.message
        assert metrics.proj_px(wire.pose_from_pb(answer.pose), T, CAMERA, obj.vertices) < 0.01


@pytest.mark.parametrize("crop, size, fix", [
    (pb.Crop(x=600, y=0, width=64, height=64), None, "reaches past the 640x480 frame"),
    (pb.Crop(x=0, y=0, width=64, height=0), None, "crop width and height must be positive"),
    (pb.Crop(x=0, y=0, width=64, height=64), (96, 64), "the crop is 64x64"),
])
def test_a_bad_crop_is_refused_saying_why(world, crop, size, fix):
    stub, rgb, _, _ = world
    req = request(rgb, crop, estimator="pnp")
    if size is not None:
        req.image.CopyFrom(pb.Image(encoding=pb.Image.PNG, data=png(rgb[:size[1], :size[0]]), width=size[0],
                                    height=size[1]))
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(req)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and fix in err.value.details()
    req.ClearField("intrinsics")
    req.image.CopyFrom(pb.Image(encoding=pb.Image.PNG, data=png(rgb[:64, :64]), width=64, height=64))
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(req)
    assert "a crop needs the full frame's intrinsics" in err.value.details()


def test_the_projection_std_is_the_covariance_through_the_projection():
    T = se3.make(so3.exp(np.array([0.3, -0.2, 0.1])), np.array([0.05, -0.02, 0.7]))
    corners = bbox_corners(np.random.default_rng(0).uniform(-0.05, 0.05, (50, 3)))
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 4e-6])
    J = np.zeros((len(corners), 2, 6))  # by finite differences of the wire's left perturbation
    for k in range(6):
        e = np.zeros(6)
        e[k] = 1e-6
        Tk = se3.make(so3.exp(e[:3]) @ T[:3, :3], T[:3, 3] + e[3:])
        J[:, :, k] = (CAMERA.project(corners @ Tk[:3, :3].T + Tk[:3, 3])
                      - CAMERA.project(corners @ T[:3, :3].T + T[:3, 3])) / 1e-6
    expected = np.sqrt(np.einsum("nia,ab,nib->ni", J, cov, J))
    assert np.allclose(projection_std_px(CAMERA, corners, T, cov), expected, rtol=1e-4)


def test_the_crop_holds_the_box_grown_by_its_uncertainty_and_goes_whole_when_it_cannot():
    corners = bbox_corners(np.random.default_rng(1).uniform(-0.04, 0.04, (50, 3)))
    T = se3.make(np.eye(3), np.array([0.0, 0.0, 1.0]))
    uv = CAMERA.project(corners + T[:3, 3])
    sure, unsure = (crop_rect(CAMERA, corners, T, wire.diagonal_covariance(np.radians(r), m)) for r, m in
                    ((0.5, 0.001), (3.0, 0.01)))
    for x, y, w, h in (sure, unsure):
        assert x % 16 == 0 and y % 16 == 0 and x <= uv[:, 0].min() - 24 and x + w >= uv[:, 0].max() + 24
        assert y <= uv[:, 1].min() - 24 and y + h >= uv[:, 1].max() + 24
    assert unsure[2] > sure[2] and unsure[3] > sure[3]
    assert crop_rect(CAMERA, corners, T, wire.diagonal_covariance(0.5, 1.0)) is None  # covers the frame
    assert crop_rect(CAMERA, corners, se3.make(np.eye(3), np.array([5.0, 0.0, 1.0])), None) is None  # out of view
    assert crop_rect(CAMERA, corners, se3.make(np.eye(3), np.array([0.0, 0.0, -1.0])), None) is None  # behind


class Held:
    """A tracker that holds one pose and covariance."""

    camera = CAMERA

    def __init__(self, T, cov):
        self.T, self.cov = T, cov

    def pose_at(self, t_ns):
        return self.T

    def pose_covariance_at(self, t_ns):
        return self.cov


def test_the_sdk_sends_the_whole_frame_first_and_after_a_loss():
    corners = bbox_corners(np.random.default_rng(1).uniform(-0.04, 0.04, (50, 3)))
    tracker = Held(se3.make(np.eye(3), np.array([0.0, 0.0, 1.0])), PRIOR_COV)
    crop = request_crop(tracker, RefinementRequest(0, 3, "refine"), corners)
    assert crop is not None and crop.width < CAMERA.width
    for reason in ("init", "failure"):
        assert request_crop(tracker, RefinementRequest(0, 3, reason), corners) is None
    assert request_crop(tracker, RefinementRequest(0, 3, "refine"), corners, CropOptions(enabled=False)) is None
    assert request_crop(Held(None, None), RefinementRequest(0, 3, "refine"), corners) is None
