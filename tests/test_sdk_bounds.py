"""The client SDK stays bounded (issue 20, items 6 and 8): it never sends a frame the server's message limit
would refuse (gRPC ends the whole Track stream on one) nor more than `max_in_flight` requests, and what it keeps
per frame or per IMU sample does not grow with the length of the session."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from client_sdk import TrackerOptions
from client_sdk.interceptor import MAX_KEPT, LatencyInterceptor
from client_sdk.transport import TrackClient, TransportOptions, make_request
from estimators.base import EstimateInput, EstimateOutput, Estimator, Status
from estimators.registry import EstimatorRegistry
from flextrack.testing.tracker_world import Motion, drive
from flextrack.v1 import pose_estimation_pb2 as pb
from service.server import BackgroundServer


class Gate(Estimator):
    kind, version = "gate", "1"

    def __init__(self):
        super().__init__("gate", ["obj"])
        self.open = threading.Event()
        self.open.set()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        self.open.wait(30)
        return EstimateOutput(Status.OK, np.eye(4), 1.0)


class Inbox:
    def __init__(self):
        self.responses, self.failures, self.cond = [], [], threading.Condition()

    def on_response(self, response):
        with self.cond:
            self.responses.append(response)
            self.cond.notify_all()

    def on_failure(self, frame_id, why):
        with self.cond:
            self.failures.append((frame_id, why))
            self.cond.notify_all()

    def wait(self, predicate, timeout_s=10.0) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout_s)


def test_a_frame_over_the_message_limit_is_refused_locally_and_the_stream_goes_on():
    estimator = Gate()
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0) as srv:
        inbox = Inbox()
        with TrackClient(srv.address, inbox.on_response, inbox.on_failure) as client:
            assert client.wait_connected(10)
            assert TransportOptions().max_message_bytes == 8 * 1024 * 1024  # the server's default limit
            big = make_request(frame_id=1, capture_time_ns=1, client_state=bytes(9 << 20))
            assert not client.submit(big)
            assert inbox.failures and inbox.failures[0][0] == 1 and "message limit" in inbox.failures[0][1]
            assert client.submit(make_request(frame_id=2, capture_time_ns=2))  # the same stream still answers
            assert inbox.wait(lambda: inbox.responses)
            assert inbox.responses[0].frame_id == 2 and inbox.responses[0].status == pb.EstimateResponse.OK
            assert client.reconnects == 0 and len(inbox.failures) == 1


def test_no_more_than_max_in_flight_requests_are_sent():
    estimator = Gate()
    estimator.open.clear()
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0) as srv:
        inbox = Inbox()
        options = TransportOptions(max_in_flight=2, request_timeout_s=30.0)
        with TrackClient(srv.address, inbox.on_response, inbox.on_failure, options=options) as client:
            assert client.wait_connected(10)
            assert client.submit(make_request(frame_id=1, capture_time_ns=1))
            assert client.submit(make_request(frame_id=2, capture_time_ns=2))
            assert not client.submit(make_request(frame_id=3, capture_time_ns=3))
            assert inbox.failures == [(3, inbox.failures[0][1])] and "in flight" in inbox.failures[0][1]
            assert client.in_flight == 2
            estimator.open.set()
            assert inbox.wait(lambda: len(inbox.responses) == 2)
            assert client.in_flight == 0


class _Request:
    def __init__(self, frame_id):
        self.frame_id = frame_id

    def ByteSize(self):  # protobuf's name
        return 100_000


def test_the_interceptor_keeps_a_bounded_number_of_frames():
    live = LatencyInterceptor(live=True, sleep=lambda s: None)
    for frame_id in range(10_000):  # uplinks whose responses never come (a stream that broke each time)
        live._uplink(_Request(frame_id))
    assert len(live._uplinks) == MAX_KEPT and max(live._uplinks) == 9_999  # the newest kept
    replay = LatencyInterceptor(live=False)
    for frame_id in range(10_000):  # stamps nobody pops
        replay._uplink(_Request(frame_id))
        replay._downlink(frame_id, pb.EstimateResponse(frame_id=frame_id))
    assert len(replay.stamps) == MAX_KEPT and replay.pop_stamp(9_999) is not None and not replay._uplinks


@pytest.mark.parametrize("fusion", ["filter", "paper"])
def test_the_tracker_keeps_its_imu_buffer_bounded_over_a_long_run(fusion):
    """The tracker's per-sample buffer holds its horizon (imu_buffer_s), not the session: 60 s or 20 s alike."""
    sizes = []
    for duration_s in (20.0, 60.0):
        run = drive(Motion(), TrackerOptions(fusion=fusion), duration_s=duration_s, fps=60.0)
        sizes.append(len(run.tracker._buf))
    bound = 1.5 * 200.0 * run.tracker.options.imu_buffer_s + 2  # trimmed in chunks: up to 1.5 horizons kept
    assert max(sizes) <= bound


def test_the_transport_forgets_answered_frames():
    with BackgroundServer(EstimatorRegistry([Gate()]), grace_s=0.0) as srv:
        inbox = Inbox()
        with TrackClient(srv.address, inbox.on_response, inbox.on_failure) as client:
            assert client.wait_connected(10)
            for frame_id in range(300):
                assert client.submit(make_request(frame_id=frame_id, capture_time_ns=frame_id))
                assert inbox.wait(lambda n=frame_id: len(inbox.responses) == n + 1)
            assert client.in_flight == 0 and not inbox.failures
