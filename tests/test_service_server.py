"""The service on a real loopback server: listing, health, reflection, answers, error codes, streams."""

import math

import cv2
import grpc
import numpy as np
import pytest
import trimesh
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from estimators.base import Estimator
from estimators.gt_oracle import GtOracleEstimator
from estimators.objects import ObjectRegistry, load_object
from estimators.pnp import PnpEstimator
from estimators.registry import EstimatorRegistry
from flextrack import wire
from flextrack.formats import sequence as sequence_io
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.testing.toy_sequence import write_orbit_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.server import BackgroundServer

CAMERA = PinholeCamera.linemod()
T_TRUE = se3.make(so3.exp(np.array([0.2, 2.5, -0.3])), np.array([-0.04, 0.03, 0.7]))


class Broken(Estimator):
    """Fails the way a buggy estimator would."""

    kind = "broken"

    def estimate(self, inp):
        raise RuntimeError("secret detail /home/user/model.onnx")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    trimesh.creation.box(extents=(90.0, 50.0, 30.0)).export(root / "box.ply")
    objects = ObjectRegistry([load_object("box", root / "box.ply")])
    seq = write_orbit_sequence(root / "seqs" / "orbit", frames=20, object_id="box")
    registry = EstimatorRegistry([GtOracleEstimator(sequence_roots=[root / "seqs"]), PnpEstimator(objects),
                                  Broken("broken")], objects=objects)
    with BackgroundServer(registry) as server:
        yield server, sequence_io.load(seq.root), objects


@pytest.fixture(scope="module")
def channel(world):
    with grpc.insecure_channel(world[0].address) as channel:
        yield channel


@pytest.fixture(scope="module")
def stub(channel):
    return pb_grpc.PoseEstimationStub(channel)


def intrinsics(camera=CAMERA) -> pb.Intrinsics:
    return wire.intrinsics_to_pb(camera)


def pnp_request(objects, frame_id=1, **kw) -> pb.EstimateRequest:
    points = objects.get("box").keypoints
    uv = CAMERA.project(se3.transform_points(T_TRUE, points))
    keypoints = [pb.Keypoint(id=i, u=u, v=v) for i, (u, v) in enumerate(uv)]
    return pb.EstimateRequest(**{"frame_id": frame_id, "estimator": "pnp", "object_id": "box",
                                 "intrinsics": intrinsics(), "keypoints": keypoints, **kw})


def oracle_request(seq, frame_id=1, **kw) -> pb.EstimateRequest:
    return pb.EstimateRequest(**{"frame_id": frame_id, "capture_time_ns": int(seq.frame_times_ns[frame_id % 20]),
                                 "estimator": "gt_oracle", "sequence": "orbit", "intrinsics": intrinsics(), **kw})


def pose_matrix(pose: pb.Pose) -> np.ndarray:
    return wire.pose_from_pb(pose)


def test_list_estimators(stub):
    infos = {e.name: e for e in stub.ListEstimators(pb.ListEstimatorsRequest()).estimators}
    assert {"gt_oracle", "pnp"} <= set(infos)
    assert infos["gt_oracle"].kind == "gt_oracle" and infos["gt_oracle"].is_default and infos["gt_oracle"].ready
    assert infos["pnp"].objects == ["box"] and infos["pnp"].version == "1.0"
    assert list(infos["gt_oracle"].objects) == ["box"]


def test_health_is_serving(channel):
    health = health_pb2_grpc.HealthStub(channel)
    for service in ("", "flextrack.v1.PoseEstimation"):
        reply = health.Check(health_pb2.HealthCheckRequest(service=service), timeout=30)
        assert reply.status == health_pb2.HealthCheckResponse.SERVING


def test_reflection_lists_the_service(channel):
    stub = reflection_pb2_grpc.ServerReflectionStub(channel)
    replies = stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=30)
    names = {s.name for reply in replies for s in reply.list_services_response.service}
    assert "flextrack.v1.PoseEstimation" in names and "grpc.health.v1.Health" in names


def test_oracle_answers_the_ground_truth_exactly(stub, world):
    _, seq, _ = world
    for frame_id in (0, 7, 19):
        response = stub.Estimate(oracle_request(seq, frame_id), timeout=30)
        assert response.status == pb.EstimateResponse.OK and response.frame_id == frame_id
        q, t = se3.to_quat_translation(seq.gt_T_CO[frame_id])
        p = response.pose
        assert [p.qw, p.qx, p.qy, p.qz] == q.tolist() and [p.tx, p.ty, p.tz] == t.tolist()
        assert response.capture_time_ns == seq.frame_times_ns[frame_id]
        assert response.estimator == "gt_oracle@1.0" and response.server_time_ms > 0


def test_pnp_recovers_a_known_pose(stub, world):
    response = stub.Estimate(pnp_request(world[2]), timeout=30)
    assert response.status == pb.EstimateResponse.OK, response.message
    T = pose_matrix(response.pose)
    assert metrics.re_deg(T, T_TRUE) < 0.05 and metrics.te_mm(T, T_TRUE) < 0.5
    assert response.confidence > 0.99 and {"decode", "estimate", "pnp"} <= set(response.stage_ms)


def test_object_out_of_view_is_a_status_not_an_error(stub, world):
    response = stub.Estimate(oracle_request(world[1], capture_time_ns=1), timeout=30)
    assert response.status == pb.EstimateResponse.OBJECT_NOT_FOUND and "no ground truth" in response.message


def _jpeg(width, height) -> bytes:
    return cv2.imencode(".jpg", np.zeros((height, width, 3), np.uint8))[1].tobytes()


# (name, request edits on a valid pnp or oracle request, expected gRPC code, words in the message)
BAD_INPUTS = [
    ("unknown estimator", "pnp", {"estimator": "pvnet9"}, grpc.StatusCode.NOT_FOUND, "pvnet9"),
    ("unknown object (pnp)", "pnp", {"object_id": "cup"}, grpc.StatusCode.NOT_FOUND, "cup"),
    ("unknown object (oracle)", "oracle", {"object_id": "cup"}, grpc.StatusCode.NOT_FOUND, "cup"),
    ("undecodable image", "pnp", {"image": pb.Image(encoding=pb.Image.JPEG, data=b"\xff\xd8garbage", width=640,
                                                    height=480)}, grpc.StatusCode.INVALID_ARGUMENT, "JPEG"),
    ("image size mismatch", "oracle", {"image": pb.Image(encoding=pb.Image.JPEG, data=_jpeg(320, 240), width=640,
                                                         height=480)}, grpc.StatusCode.INVALID_ARGUMENT, "320x240"),
    ("raw size mismatch", "oracle", {"image": pb.Image(encoding=pb.Image.RAW_GRAY8, data=b"\0" * 100, width=640,
                                                       height=480)}, grpc.StatusCode.INVALID_ARGUMENT, "bytes"),
    ("missing intrinsics", "pnp", {"intrinsics": pb.Intrinsics()}, grpc.StatusCode.INVALID_ARGUMENT, "intrinsics"),
    ("non-positive focal length", "pnp", {"intrinsics": pb.Intrinsics(fx=-1, fy=500, cx=1, cy=1, width=640,
                                                                      height=480)},
     grpc.StatusCode.INVALID_ARGUMENT, "fx and fy must be"),
    ("infinite intrinsics", "oracle", {"intrinsics": pb.Intrinsics(fx=math.inf, fy=500, cx=1, cy=1, width=640,
                                                                   height=480)},
     grpc.StatusCode.INVALID_ARGUMENT, "finite"),
    ("fewer than 4 keypoints", "pnp", {"keypoints": [pb.Keypoint(id=i, u=1.0, v=2.0) for i in range(3)]},
     grpc.StatusCode.INVALID_ARGUMENT, "at least 4"),
    ("NaN keypoint", "pnp", {"keypoints": [pb.Keypoint(id=i, u=math.nan, v=2.0) for i in range(5)]},
     grpc.StatusCode.INVALID_ARGUMENT, "finite"),
    ("unknown sequence", "oracle", {"sequence": "V1_02"}, grpc.StatusCode.FAILED_PRECONDITION, "V1_02"),
    ("estimator bug", "oracle", {"estimator": "broken"}, grpc.StatusCode.INTERNAL, "server log"),
]


def bad_request(world, base, edits, frame_id=1):
    _, seq, objects = world
    request = pnp_request(objects, frame_id) if base == "pnp" else oracle_request(seq, frame_id)
    for field, value in edits.items():
        if isinstance(value, list):
            del getattr(request, field)[:]
            getattr(request, field).extend(value)
        elif isinstance(value, str):
            setattr(request, field, value)
        else:
            getattr(request, field).CopyFrom(value)
    return request


@pytest.mark.parametrize("name, base, edits, code, words", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_input_gets_its_code_and_a_message(stub, world, name, base, edits, code, words):
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(bad_request(world, base, edits), timeout=30)
    assert err.value.code() == code
    assert words in err.value.details() and "Traceback" not in err.value.details()
    assert "secret" not in err.value.details()


def test_track_stream_answers_bad_frames_with_a_status_and_goes_on(stub, world):
    seq = world[1]
    requests = []
    for k, (_, base, edits, code, _) in enumerate(BAD_INPUTS):
        requests += [bad_request(world, base, edits, frame_id=2 * k), oracle_request(seq, frame_id=2 * k + 1)]
    responses = list(stub.Track(iter(requests), timeout=10))
    assert [r.frame_id for r in responses] == [r.frame_id for r in requests]
    for k, (name, *_, code, words) in enumerate(BAD_INPUTS):
        bad, good = responses[2 * k], responses[2 * k + 1]
        expected = pb.EstimateResponse.INTERNAL if code == grpc.StatusCode.INTERNAL else pb.EstimateResponse.INVALID_INPUT
        assert bad.status == expected and words in bad.message, name
        assert good.status == pb.EstimateResponse.OK, name


def test_track_stream_of_50_answers_in_order(stub, world):
    _, seq, objects = world
    requests = [pnp_request(objects, k) if k % 3 == 0 else oracle_request(seq, k) for k in range(50)]
    responses = list(stub.Track(iter(requests), timeout=10))
    assert [r.frame_id for r in responses] == list(range(50))
    assert all(r.status == pb.EstimateResponse.OK for r in responses)
    assert [r.estimator for r in responses[:3]] == ["pnp@1.0", "gt_oracle@1.0", "gt_oracle@1.0"]


def test_message_size_limit_is_8_mib(stub, world):
    _, seq, _ = world
    big = pb.Image(encoding=pb.Image.RAW_RGB8, data=bytes(1280 * 1440 * 3), width=1280, height=1440)  # 5.5 MB
    response = stub.Estimate(oracle_request(seq, intrinsics=pb.Intrinsics(), image=big), timeout=10)
    assert response.status == pb.EstimateResponse.OK  # above gRPC's 4 MiB default
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(oracle_request(seq, client_state=bytes(9 << 20)), timeout=10)
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
