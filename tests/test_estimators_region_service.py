"""The region and chained estimators behind a real gRPC server on loopback: a good prior gets a pose
with its covariance; a prior that is not a rigid transform, or whose covariance is not positive
definite, is refused with INVALID_ARGUMENT; region alone refuses a request without a prior, while
the chained estimator answers it with its global part."""

import cv2
import grpc
import numpy as np
import pytest

from estimators.base import EstimateOutput, Estimator, Status
from estimators.chained import ChainedEstimator
from estimators.objects import ObjectRegistry
from estimators.registry import EstimatorRegistry
from flextrack import wire
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.testing.region_scene import rendered_region_scene
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.server import BackgroundServer

CAMERA = PinholeCamera.linemod()


class Fixed(Estimator):
    """A global estimator that answers every frame with one pose."""

    kind = "fixed"
    uses_image = True

    def __init__(self, T):
        super().__init__("fixed", ["default"])
        self.T = T

    def estimate(self, inp):
        return EstimateOutput(Status.OK, self.T, 0.5, np.eye(6) * 1e-4)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    region, obj, T, image = rendered_region_scene(tmp_path_factory.mktemp("region_cache"), CAMERA)
    png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes()
    chained = ChainedEstimator("tracking", Fixed(T), region)
    registry = EstimatorRegistry([region, chained], objects=ObjectRegistry([obj]))
    with BackgroundServer(registry) as server, grpc.insecure_channel(server.address) as channel:
        yield pb_grpc.PoseEstimationStub(channel), png, T, obj


def request(png, prior=None, estimator="region", **kw):
    return pb.EstimateRequest(
        session_id="s1", frame_id=1, estimator=estimator, object_id="default", prior=prior,
        image=pb.Image(encoding=pb.Image.PNG, data=png, width=CAMERA.width, height=CAMERA.height),
        intrinsics=wire.intrinsics_to_pb(CAMERA), **kw)


def prior_pb(T, cov=None):
    return pb.PosePrior(pose=wire.pose_to_pb(T), covariance=wire.covariance_to_pb(cov))


def test_a_good_prior_gets_a_refined_pose_with_its_covariance(world):
    stub, png, T, obj = world
    T_prior = se3.make(so3.exp(np.radians([2.0, -2.0, 1.0])) @ T[:3, :3], T[:3, 3] + [0.004, -0.003, 0.005])
    answer = stub.Estimate(request(png, prior_pb(T_prior, wire.diagonal_covariance(np.radians(5), 0.01))))
    assert answer.status == pb.EstimateResponse.OK, answer.message
    T_est = wire.pose_from_pb(answer.pose)
    assert metrics.proj_px(T_est, T, CAMERA, obj.vertices) < 1.5 < metrics.proj_px(T_prior, T, CAMERA, obj.vertices)
    cov = wire.covariance_from_pb(answer.pose_covariance)
    assert cov is not None and np.all(np.linalg.eigvalsh(cov) > 0)
    assert answer.estimator.startswith("region@")


def test_a_prior_that_is_not_rigid_is_refused(world):
    stub, png, T, _ = world
    pose = wire.pose_to_pb(T)
    pose.qw *= 1.5  # a quaternion of norm != 1: a scaled rotation
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(request(png, pb.PosePrior(pose=pose)))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "rigid" in err.value.details()


@pytest.mark.parametrize("cov, why", [
    (np.diag([1e-3] * 3 + [-1e-4] * 3), "positive definite"),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1) * 0.5, "symmetric"),
])
def test_a_covariance_not_positive_definite_is_refused(world, cov, why):
    stub, png, T, _ = world
    msg = pb.PosePrior(pose=wire.pose_to_pb(T), covariance=wire.covariance_to_pb(cov))
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(request(png, msg))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and why in err.value.details()


def test_without_a_prior_region_refuses_and_the_chained_estimator_asks_its_global_part(world):
    stub, png, T, _ = world
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(request(png))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "prior" in err.value.details()
    answer = stub.Estimate(request(png, estimator="tracking"))
    assert answer.status == pb.EstimateResponse.OK
    np.testing.assert_allclose(wire.pose_from_pb(answer.pose), T, atol=1e-6)
    assert "global" in answer.stage_ms


def test_a_prior_claimed_almost_exact_still_gets_a_positive_definite_covariance(world):
    """A valid but extreme prior (1e-15 std) must not cancel the image's own information out of the
    answer's covariance: region reports the image's evidence alone, never anything the wire refuses."""
    stub, png, T, _ = world
    answer = stub.Estimate(request(png, prior_pb(T, np.eye(6) * 1e-30)))
    assert answer.status == pb.EstimateResponse.OK, answer.message
    cov = wire.covariance_from_pb(answer.pose_covariance)  # BadCovariance if it were not SPD
    assert cov is not None and np.all(np.linalg.eigvalsh(cov) > 0)


class Broken(Fixed):
    """An estimator whose covariance is not positive definite (a plug-in's bug)."""

    kind = "broken"

    def estimate(self, inp):
        return EstimateOutput(Status.OK, self.T, 0.5, np.diag([1e-4] * 3 + [-1e-4] * 3), message="found it")


def test_a_bad_covariance_from_an_estimator_is_withheld_and_said(world):
    from service.estimation import EstimationService

    _, png, T, obj = world
    service = EstimationService(EstimatorRegistry([Broken(T)], objects=ObjectRegistry([obj])))
    answer = service.answer(request(png, estimator="fixed"))
    assert answer.status == pb.EstimateResponse.OK and answer.HasField("pose")
    assert not answer.HasField("pose_covariance")  # the client falls back on its documented default
    assert answer.message.startswith("found it; covariance withheld") and "positive definite" in answer.message
