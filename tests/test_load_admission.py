"""Overload: past the admission bound the server refuses frames (Track: UNAVAILABLE, Estimate:
RESOURCE_EXHAUSTED), stays up, never lets more frames in than the bound, and counts it all in
its Prometheus metrics."""

from __future__ import annotations

import itertools
import threading
import time
import urllib.request

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from estimators.base import EstimateInput, EstimateOutput, Estimator, Status
from estimators.registry import EstimatorRegistry
from flextrack.loadtest import runner, workload
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.admission import AdmissionInterceptor
from service.hardening import Hardening
from service.metrics import LOADING_ESTIMATORS
from service.server import BackgroundServer


class SlowEstimator(Estimator):
    """A backend that needs 20 ms a frame off the GIL (as a network on an accelerator would), or, with a
    `gate`, holds every frame until the gate opens. Its counters are kept under a lock (worker threads)."""

    kind, version = "slow", "1"

    def __init__(self, seconds: float = 0.02, gate: threading.Event | None = None):
        super().__init__("slow", ["obj"])
        self.seconds, self.gate, self.in_progress, self.most_in_progress = seconds, gate, 0, 0
        self.changed = threading.Condition()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        with self.changed:
            self.in_progress += 1
            self.most_in_progress = max(self.most_in_progress, self.in_progress)
            self.changed.notify_all()
        if self.gate is not None:
            self.gate.wait(30)
        else:
            time.sleep(self.seconds)
        with self.changed:
            self.in_progress -= 1
            self.changed.notify_all()
        return EstimateOutput(Status.OK, np.eye(4), 1.0)

    def wait_in_progress(self, n: int, timeout_s: float = 30) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: self.in_progress >= n, timeout_s), f"{n} frames never in progress"


@pytest.fixture()
def slow_server():
    estimator, hardening = SlowEstimator(), Hardening(max_queue=2)
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, workers=4, hardening=hardening) as srv:
        yield srv.address, estimator, hardening.metrics


@pytest.mark.parametrize("rpc", ["track", "estimate"])
def test_overload_refuses_the_excess_and_keeps_serving(rpc):
    """Two frames held in the estimator fill the bound (max_queue=2): a third is refused at once (Track: a
    response with status UNAVAILABLE, the stream goes on; Estimate: RESOURCE_EXHAUSTED); once the two are
    let go, both are answered and the server serves again. Every step waits on an event, not a clock."""
    gate = threading.Event()
    estimator, hardening = SlowEstimator(gate=gate), Hardening(max_queue=2)
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, workers=4, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        stub = pb_grpc.PoseEstimationStub(channel)
        try:
            held = [stub.Estimate.future(pb.EstimateRequest(frame_id=i), timeout=30) for i in range(2)]
            estimator.wait_in_progress(2)
            if rpc == "track":
                reply = next(iter(stub.Track(iter([pb.EstimateRequest(frame_id=3)]), timeout=30)))
                assert reply.status == pb.EstimateResponse.UNAVAILABLE and reply.frame_id == 3
            else:
                with pytest.raises(grpc.RpcError) as refused:
                    stub.Estimate(pb.EstimateRequest(frame_id=3), timeout=30)
                assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        finally:
            gate.set()
        assert [f.result().status for f in held] == [pb.EstimateResponse.OK] * 2
        reply = stub.Estimate(pb.EstimateRequest(frame_id=7), timeout=30)  # still up and answering
        assert reply.status == pb.EstimateResponse.OK
    assert estimator.most_in_progress == 2  # the bound held: never more than 2 frames let in
    method = "Track" if rpc == "track" else "Estimate"
    assert hardening.metrics.count("RESOURCE_EXHAUSTED", method, "slow") == 1
    assert hardening.metrics.count("OK", "Estimate", "slow") == 3


def test_overload_under_real_load_keeps_the_bound(slow_server):
    """8 clients x 30 FPS against 2 frames in progress x 50 frames/s: whatever the machine's speed, no more
    than 2 frames are ever let in, every answer is OK or a refusal, and the server counted each."""
    address, estimator, metrics = slow_server
    spec = runner.LoadSpec((address,), clients=8, fps=30, duration_s=1.5, warmup_s=0.3, rpc="estimate")
    result = runner.run(spec, workload.synthetic(payload_kb=20, frames=4))
    assert {s.outcome for s in result.samples} <= {"OK", "grpc:RESOURCE_EXHAUSTED"}
    assert estimator.most_in_progress <= 2
    assert metrics.count("RESOURCE_EXHAUSTED", "Estimate", "slow") >= sum(
        s.outcome == "grpc:RESOURCE_EXHAUSTED" for s in result.samples)
    assert metrics.count("OK", "Estimate", "slow") >= sum(s.outcome == "OK" for s in result.samples)


def test_unbounded_queue_lets_every_frame_in(slow_server):
    estimator, hardening = SlowEstimator(0.005), Hardening()
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, hardening=hardening) as srv:
        spec = runner.LoadSpec((srv.address,), clients=3, fps=30, duration_s=0.5, warmup_s=0.2)
        result = runner.run(spec, workload.synthetic(payload_kb=5, frames=2))
    assert result.samples and {s.outcome for s in result.samples} == {"OK"}
    assert hardening.metrics.count("RESOURCE_EXHAUSTED") == 0


def test_metrics_endpoint_serves_counts_latency_and_queue_depth(slow_server):
    address, _, metrics = slow_server
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.PoseEstimationStub(channel)
        list(stub.Track(iter([pb.EstimateRequest(frame_id=i) for i in range(3)]), timeout=30))
        with pytest.raises(grpc.RpcError):
            stub.Estimate(pb.EstimateRequest(estimator="nope"), timeout=30)
    http_server, _ = metrics.serve_http(0, "127.0.0.1")
    try:
        text = urllib.request.urlopen(f"http://127.0.0.1:{http_server.server_port}/metrics", timeout=30).read().decode()
    finally:
        http_server.shutdown()
    assert 'flextrack_requests_total{code="OK",estimator="slow",method="Track"} 3.0' in text
    assert 'flextrack_requests_total{code="NOT_FOUND",estimator="(unknown)",method="Estimate"} 1.0' in text  # not the raw name
    assert 'flextrack_request_latency_seconds_count{estimator="slow",method="Track"} 3.0' in text
    assert 'flextrack_queue_depth{estimator="slow"} 0.0' in text


def test_before_the_estimators_are_loaded_every_name_counts_under_one_label():
    """The server takes calls while its estimators load (health NOT_SERVING): a client's raw estimator names
    must not key queue depths or metrics series then either."""
    admission = AdmissionInterceptor(4)
    names = {admission.resolve(name) for name in ("pnp", "", "x" * 10_000, "unknown:1")}
    assert names == {LOADING_ESTIMATORS}


def test_negative_bound_is_refused():
    with pytest.raises(ValueError, match="max_queue, max_streams and retry_pushback_ms"):
        AdmissionInterceptor(-1)


def test_stream_bound_refuses_new_devices_at_once_and_keeps_health_open():
    estimator, hardening = SlowEstimator(0.002), Hardening(max_streams=2)
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, hardening=hardening) as srv:
        spec = runner.LoadSpec((srv.address,), clients=5, fps=30, duration_s=1.0, warmup_s=0.0,
                               await_admission=True)
        result = runner.run(spec, workload.synthetic(payload_kb=5, frames=2))
        with grpc.insecure_channel(srv.address) as channel:
            health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=30)
    served = {s.client for s in result.samples if s.outcome == "OK"}
    refused = {s.client for s in result.samples if s.outcome == "grpc:RESOURCE_EXHAUSTED"}
    assert len(served) == 2 and refused and refused <= set(range(5)) - served  # the first two streams stay
    assert health.status == health_pb2.HealthCheckResponse.SERVING
    refusals = sum(s.client in refused for s in result.samples)
    assert hardening.metrics.count("RESOURCE_EXHAUSTED", "Track", "-") >= refusals
    # the refusals ask for ~2 s (1-3 s) before a retry, and the load generator waits at least that long between
    # a refused client's attempts, however slow the machine (backoff alone would retry after 50, 100, 200 ms)
    for c in refused:
        sent = sorted(s.sent_s for s in result.samples if s.client == c)
        assert all(b - a >= 1.0 for a, b in itertools.pairwise(sent)), sent


def _no_frames_until(stop: threading.Event):
    stop.wait(10)
    yield from ()


def test_a_refused_stream_says_when_to_retry_jittered():
    hardening = Hardening(max_streams=1, retry_pushback_ms=400)
    with BackgroundServer(EstimatorRegistry([SlowEstimator()]), grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        stub, stop = pb_grpc.PoseEstimationStub(channel), threading.Event()
        held = stub.Track(_no_frames_until(stop))  # the only slot
        try:
            held.initial_metadata()
            pushbacks = []
            for _ in range(6):
                with pytest.raises(grpc.RpcError) as refused:
                    list(stub.Track(iter(()), timeout=30))
                assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
                pushbacks.append(dict(refused.value.trailing_metadata())["grpc-retry-pushback-ms"])
        finally:  # the request generator ends however the test goes (no thread left waiting on it)
            stop.set()
            held.cancel()
    assert all(200 <= int(ms) <= 600 for ms in pushbacks) and len(set(pushbacks)) > 1


def test_the_refusal_probe_times_a_full_server_and_passes_an_open_one():
    from flextrack.benchmarks.refusal_probe import probe

    estimator, hardening = SlowEstimator(0.002), Hardening(max_streams=1)
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, hardening=hardening) as srv:
        assert probe(srv.address, 0.3, 0.05)["admitted"] >= 1  # a free slot: admitted
        stop = threading.Event()
        with grpc.insecure_channel(srv.address) as channel:  # a device holding the only slot
            held = pb_grpc.PoseEstimationStub(channel).Track(_no_frames_until(stop))
            try:
                held.initial_metadata()
                full = probe(srv.address, 0.3, 0.05)
            finally:
                stop.set()
                held.cancel()
    assert full["admitted"] == 0 and len(full["refused_ms"]) >= 2 and not full["other"]
    assert all(0 < ms < 5000 for ms in full["refused_ms"])
