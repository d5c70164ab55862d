"""Property-based fuzzing of a real loopback server: thousands of random and malformed requests
(valid protobuf with wild values, and bytes that are not protobuf at all) through the same
interceptors the server runs with. The server must not crash, must never send an exception trace,
and every answer must be a defined status: a response status for the Track stream (one answer per
frame, in order) and a gRPC code for unary calls."""

from __future__ import annotations

import grpc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimators.registry import EstimatorRegistry
from flextrack.benchmarks.toy_sequence import write_orbit_sequence
from flextrack.loadtest.workload import synthetic
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.cli import DEFAULT_CONFIG
from service.hardening import Hardening
from service.server import BackgroundServer

TOKEN = "fuzz-token"
METADATA = (("authorization", f"Bearer {TOKEN}"),)
# Codes a unary call may fail with: each says what the caller did wrong or that it should retry.
DEFINED_CODES = {grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND, grpc.StatusCode.FAILED_PRECONDITION,
                 grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.UNAVAILABLE}
DEFINED_STATUSES = set(pb.EstimateResponse.Status.values()) - {pb.EstimateResponse.STATUS_UNSPECIFIED}
TRACE_MARKS = ("Traceback", 'File "', "Error(", "line ")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    seq = write_orbit_sequence(tmp_path_factory.mktemp("seq") / "orbit", frames=20)
    registry = EstimatorRegistry.from_config(DEFAULT_CONFIG)
    registry.get("gt_oracle").add_sequence(seq.root)
    registry.get("gt_noisy").add_sequence(seq.root)
    hardening = Hardening(tokens=[TOKEN], max_queue=64)
    with BackgroundServer(registry, grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        yield channel, seq


def _no_trace(text: str) -> bool:
    return not any(mark in text for mark in TRACE_MARKS)


_finite_or_wild = st.one_of(st.floats(-1e4, 1e4), st.floats(allow_nan=True, allow_infinity=True))
_small_jpeg = pb.EstimateRequest.FromString(synthetic(0, frames=1).templates[0].body).image.data


@st.composite
def images(draw):
    encoding = draw(st.integers(0, 7))  # 5..7: values the enum does not have
    width, height = draw(st.sampled_from([0, 1, 8, 640, 100_000])), draw(st.sampled_from([0, 1, 6, 480, 100_000]))
    data = draw(st.one_of(st.binary(max_size=300), st.just(_small_jpeg), st.just(b"\x89PNG\r\n\x1a\n" + b"\0" * 40),
                          st.just(bytes(width * height * 3) if width * height <= 10_000 else b"")))
    return pb.Image(encoding=encoding, data=data, width=width, height=height)


@st.composite
def requests(draw, seq):
    t0, t1 = int(seq.frame_times_ns[0]), int(seq.frame_times_ns[-1])
    return pb.EstimateRequest(
        session_id=draw(st.text(max_size=12)),
        frame_id=draw(st.integers(0, 2**64 - 1)),
        capture_time_ns=draw(st.one_of(st.integers(t0, t1), st.integers(-(2**63), 2**63 - 1))),
        estimator=draw(st.one_of(st.sampled_from(["", "gt_oracle", "gt_noisy", "pnp"]), st.text(max_size=10))),
        object_id=draw(st.one_of(st.sampled_from(["", "toy", "default"]), st.text(max_size=10))),
        sequence=draw(st.one_of(st.sampled_from(["", "orbit"]), st.text(max_size=10))),
        image=draw(st.one_of(st.just(pb.Image()), images())),
        intrinsics=pb.Intrinsics(
            fx=draw(_finite_or_wild), fy=draw(_finite_or_wild), cx=draw(_finite_or_wild), cy=draw(_finite_or_wild),
            width=draw(st.sampled_from([0, 640, 7])), height=draw(st.sampled_from([0, 480, 5])),
            distortion=draw(st.lists(_finite_or_wild, max_size=15))),
        keypoints=[pb.Keypoint(id=i, u=u, v=v) for i, u, v in draw(st.lists(
            st.tuples(st.integers(0, 2**32 - 1), _finite_or_wild, _finite_or_wild), max_size=12))],
        client_state=draw(st.binary(max_size=64)),
    )


def _fuzz_settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


def test_track_answers_every_frame_in_order_with_a_defined_status(server):
    channel, seq = server
    stub = pb_grpc.PoseEstimationStub(channel)

    @_fuzz_settings(200)
    @given(st.lists(requests(seq), min_size=1, max_size=25))
    def check(batch):
        answers = list(stub.Track(iter(batch), timeout=30, metadata=METADATA))
        assert [a.frame_id for a in answers] == [r.frame_id for r in batch]
        for answer in answers:
            assert answer.status in DEFINED_STATUSES
            assert _no_trace(answer.message), answer.message
            if answer.status == pb.EstimateResponse.OK:
                q = [answer.pose.qw, answer.pose.qx, answer.pose.qy, answer.pose.qz]
                assert np.isclose(np.linalg.norm(q), 1.0) and np.isfinite(answer.pose.tz)

    check()


def test_estimate_fails_only_with_defined_codes_and_no_trace(server):
    channel, seq = server
    stub = pb_grpc.PoseEstimationStub(channel)

    @_fuzz_settings(400)
    @given(requests(seq))
    def check(request):
        try:
            answer = stub.Estimate(request, timeout=30, metadata=METADATA)
        except grpc.RpcError as exc:
            assert exc.code() in DEFINED_CODES, (exc.code(), exc.details())
            assert _no_trace(exc.details() or ""), exc.details()
        else:
            assert answer.status in DEFINED_STATUSES and _no_trace(answer.message)

    check()


def test_bytes_that_are_not_protobuf_are_refused_cleanly(server):
    channel, _ = server
    estimate = channel.unary_unary("/flextrack.v1.PoseEstimation/Estimate", request_serializer=None,
                                   response_deserializer=pb.EstimateResponse.FromString)
    track = channel.stream_stream("/flextrack.v1.PoseEstimation/Track", request_serializer=None,
                                  response_deserializer=pb.EstimateResponse.FromString)

    @_fuzz_settings(150)
    @given(st.binary(min_size=1, max_size=200))
    def check(raw):
        try:
            pb.EstimateRequest.FromString(raw)
        except Exception:  # noqa: BLE001 - only bytes protobuf cannot parse are of interest here
            with pytest.raises(grpc.RpcError) as err:
                estimate(raw, timeout=10, metadata=METADATA)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and _no_trace(err.value.details())
            # in a stream the bad frame is answered and the stream goes on
            answers = list(track(iter([raw, pb.EstimateRequest(frame_id=5).SerializeToString()]), timeout=10,
                                 metadata=METADATA))
            assert len(answers) == 2 and answers[0].status == pb.EstimateResponse.INVALID_INPUT
            assert answers[1].frame_id == 5 and _no_trace(answers[0].message)

    check()
