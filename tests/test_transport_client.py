"""The latency interceptor and the Track client against a real server on a loopback port."""

import threading
import time

import grpc
import numpy as np
import pytest

from client_sdk import network_model as nm
from client_sdk.interceptor import LatencyInterceptor
from client_sdk.transport import TrackClient, TransportOptions, make_request, retry_pushback_s
from estimators.registry import EstimatorRegistry
from flextrack.runners.payload import PAPER_JPEG_BYTES, stand_in_jpeg
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.hardening import Hardening
from service.metrics import ServiceMetrics
from service.server import BackgroundServer

FAST = TransportOptions(request_timeout_s=2.0, connect_timeout_s=0.2, backoff_initial_s=0.02, backoff_max_s=0.2)


@pytest.fixture
def server():
    with BackgroundServer(EstimatorRegistry(), grace_s=0.0) as srv:  # no estimator: every answer is a status, never a break
        yield srv


def _request(frame_id: int) -> pb.EstimateRequest:
    return make_request(frame_id=frame_id, capture_time_ns=frame_id * 1000, image=stand_in_jpeg(),
                        width=640, height=480, client_state=b"s" * 10 * 1024)


class _Inbox:
    def __init__(self):
        self.responses, self.failures = [], []
        self.cond = threading.Condition()

    def on_response(self, r):
        with self.cond:
            self.responses.append(r)
            self.cond.notify_all()

    def on_failure(self, frame_id, reason):
        with self.cond:
            self.failures.append((frame_id, reason))
            self.cond.notify_all()

    def wait(self, pred, timeout=10.0):
        with self.cond:
            assert self.cond.wait_for(pred, timeout), "timed out"


def test_replay_mode_stamps_without_sleeping(server):
    opts = nm.NetworkOptions(seed=3)
    slept = []
    ic = LatencyInterceptor(opts, live=False, sleep=slept.append)
    with grpc.insecure_channel(server.address) as ch:
        stub = pb_grpc.PoseEstimationStub(grpc.intercept_channel(ch, ic))
        responses = list(stub.Track(iter([_request(1), _request(2)])))
    assert [r.frame_id for r in responses] == [1, 2]
    assert slept == []
    for frame_id in (1, 2):
        stamp = ic.pop_stamp(frame_id)
        assert stamp == nm.sample(opts, frame_id, 0, 0)  # fixed 100 kB payload: size does not matter
        assert 35.6e6 <= stamp.round_trip_ns <= 65.7e6
    assert ic.pop_stamp(1) is None


def test_live_mode_sleeps_both_legs_and_uses_the_real_size(server):
    opts = nm.NetworkOptions(fixed_payload_bytes=None, seed=1)
    slept, seen = [], []
    ic = LatencyInterceptor(opts, live=True, sleep=slept.append, on_delay=lambda f, d: seen.append((f, d)))
    request = _request(5)
    assert request.ByteSize() > PAPER_JPEG_BYTES + 10 * 1024
    with grpc.insecure_channel(server.address) as ch:
        stub = pb_grpc.PoseEstimationStub(grpc.intercept_channel(ch, ic))
        with pytest.raises(grpc.RpcError) as err:  # no estimator: the unary call fails with a code
            stub.Estimate(request)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
        list(stub.Track(iter([request])))
    expected = nm.sample(opts, 5, request.ByteSize())
    assert slept[0] == pytest.approx(expected.uplink_ns * 1e-9)  # unary: uplink only, the call failed
    assert slept[1:] == pytest.approx([expected.uplink_ns * 1e-9, expected.downlink_ns * 1e-9])
    assert seen == [(5, expected)]


def test_track_client_survives_server_stop_and_restart():
    inbox = _Inbox()
    registry = EstimatorRegistry()
    srv = BackgroundServer(registry).start()
    port = srv.port
    with TrackClient(srv.address, inbox.on_response, inbox.on_failure, options=FAST) as client:
        assert client.wait_connected(5.0)
        assert client.submit(_request(1))
        assert client.submit(_request(2))
        inbox.wait(lambda: len(inbox.responses) == 2)
        assert [r.frame_id for r in inbox.responses] == [1, 2]  # in order
        assert inbox.responses[0].status == pb.EstimateResponse.INVALID_INPUT  # an answer, not a break

        srv.stop()
        deadline = time.monotonic() + 30.0  # polled; the bound only stops a broken test from hanging
        while client.connected and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not client.connected
        assert not client.submit(_request(3))  # refused, not raised

        srv = BackgroundServer(registry, port=port).start()
        try:
            assert client.wait_connected(10.0)
            assert client.reconnects >= 1
            assert client.submit(_request(4))
            inbox.wait(lambda: len(inbox.responses) == 3)
            assert inbox.responses[2].frame_id == 4
        finally:
            srv.stop()
    assert inbox.failures == []


def test_request_in_flight_when_the_server_dies_is_reported():
    inbox = _Inbox()
    srv = BackgroundServer(EstimatorRegistry(), grace_s=0.0).start()
    slow = LatencyInterceptor(nm.NetworkOptions(propagation_ms=300.0, extra_max_ms=0.0), live=True)
    client = TrackClient(srv.address, inbox.on_response, inbox.on_failure, interceptors=[slow], options=FAST).start()
    try:
        assert client.wait_connected(5.0)
        assert client.submit(_request(9))
        srv.stop()  # the request is still on its (slow) uplink
        inbox.wait(lambda: inbox.failures)
        assert inbox.failures[0][0] == 9 and inbox.failures[0][1]
        assert client.in_flight == 0
    finally:
        client.close()
        srv.stop()


def test_unreachable_backend_never_raises():
    inbox = _Inbox()
    with TrackClient("127.0.0.1:1", inbox.on_response, inbox.on_failure, options=FAST) as client:
        assert not client.wait_connected(0.3)
        assert not client.submit(_request(1))


@pytest.mark.parametrize("value, seconds", [("1500", 1.5), ("0", 0.0), ("-5", 0.0), ("nan", 0.0), ("soon", 0.0)])
def test_retry_pushback_is_read_from_the_trailer(value, seconds):
    assert retry_pushback_s((("other", "7"), ("grpc-retry-pushback-ms", value))) == seconds
    assert retry_pushback_s(None) == 0.0


class _RefusalTimes(ServiceMetrics):
    """The server's metrics, also noting when each refusal happened (under a condition the test waits on)."""

    def __init__(self):
        super().__init__()
        self.times: list[float] = []
        self.changed = threading.Condition()

    def observe(self, method, estimator, code, seconds):
        super().observe(method, estimator, code, seconds)
        if code == "RESOURCE_EXHAUSTED":
            with self.changed:
                self.times.append(time.monotonic())
                self.changed.notify_all()

    def wait_for(self, n: int, timeout_s: float = 60.0) -> list[float]:
        with self.changed:
            assert self.changed.wait_for(lambda: len(self.times) >= n, timeout_s), f"fewer than {n} refusals"
            return list(self.times[:n])


def _refusal_times(pushback_ms: float, n: int) -> list[float]:
    """A TrackClient retries against a server whose only stream slot is held: when were its first n refusals?"""
    metrics = _RefusalTimes()
    hardening = Hardening(max_streams=1, retry_pushback_ms=pushback_ms, metrics=metrics)
    stop = threading.Event()

    def no_frames():
        stop.wait(60)
        yield from ()

    with BackgroundServer(EstimatorRegistry(), grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        held = pb_grpc.PoseEstimationStub(channel).Track(no_frames())
        try:
            held.initial_metadata()
            inbox = _Inbox()
            with TrackClient(srv.address, inbox.on_response, inbox.on_failure, options=FAST):
                return metrics.wait_for(n)
        finally:  # the held stream's request generator ends whatever happens
            stop.set()
            held.cancel()


def test_track_client_waits_as_long_as_a_refusing_server_asks():
    """Event-driven: wait for the refusals themselves, then compare the gaps between them (lower bounds only,
    which a slow machine cannot break): with a 1 s pushback (jittered 0.5-1.5 s) the client waits at least
    0.5 s between tries; without one, backoff alone (20 ms doubling to 200 ms) retries."""
    patient = np.diff(_refusal_times(pushback_ms=1000, n=3))
    assert np.all(patient >= 0.5), patient
    assert len(_refusal_times(pushback_ms=0, n=4)) == 4  # without a pushback it keeps retrying on its backoff
