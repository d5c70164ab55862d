"""What real images and long runs found (issue 33), each on a real loopback server: a progressive-JPEG scan bomb and
headers Pillow would walk byte by byte are refused before any decode, repeated fields are counted before anything
walks them."""

from __future__ import annotations

import socket
import struct
import threading
import time
import urllib.request

import grpc
import numpy as np
import pytest

from estimators.base import EstimateInput, EstimateOutput, Estimator, Status
from estimators.registry import EstimatorRegistry
from flextrack.benchmarks.jpeg_bound_bench import progressive_jpeg, scan_bomb
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service import metrics, request_decoding
from service.hardening import Hardening
from service.request_decoding import MAX_JPEG_SCANS
from service.server import BackgroundServer


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


INTRINSICS = pb.Intrinsics(fx=500, fy=500, cx=320, cy=240, width=640, height=480)


class ImageEstimator(Estimator):
    """Decodes the image (uses_image) and counts the frames it was given."""

    kind, version, uses_image = "images", "1", True

    def __init__(self):
        super().__init__("images", ["obj"])
        self.calls, self._lock = 0, threading.Lock()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        with self._lock:
            self.calls += 1
        return EstimateOutput(Status.OK, np.eye(4), 1.0)


@pytest.fixture(scope="module")
def server():
    images = ImageEstimator()
    with BackgroundServer(EstimatorRegistry([images]), grace_s=0.0, hardening=Hardening()) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        yield pb_grpc.PoseEstimationStub(channel), images


@pytest.fixture(scope="module")
def jpeg():
    return progressive_jpeg(640, 480)


def _request(data: bytes, frame_id: int = 0, **fields) -> pb.EstimateRequest:
    return pb.EstimateRequest(frame_id=frame_id, estimator="images", intrinsics=INTRINSICS,
                              image=pb.Image(encoding=pb.Image.JPEG, data=data, width=640, height=480), **fields)


def test_a_scan_bomb_under_an_honest_header_is_refused_before_decoding_and_the_server_goes_on(server, jpeg,
                                                                                               monkeypatch):
    stub, images = server
    bomb = scan_bomb(jpeg, 200_000, 32)  # one AC scan 200,000 times more: 6.7 MB, within every other limit
    assert request_decoding._jpeg_size(bomb) == (640, 480) and len(bomb) < 8 * 1024 * 1024
    decodes = []
    real_decode = request_decoding._decode_rgb
    monkeypatch.setattr(request_decoding, "_decode_rgb", lambda *a: decodes.append(a) or real_decode(*a))
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(_request(bomb), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert f"at most {MAX_JPEG_SCANS} are accepted" in err.value.details()
    [answer, after] = list(stub.Track(iter([_request(bomb, 1), _request(jpeg, 2)]), timeout=30))
    assert answer.status == pb.EstimateResponse.INVALID_INPUT and "scans" in answer.message
    assert after.status == pb.EstimateResponse.OK  # the stream goes on
    assert len(decodes) == 1 and images.calls == 1  # only the honest frame was decoded and estimated
    at_limit = scan_bomb(jpeg, MAX_JPEG_SCANS - jpeg.count(b"\xff\xda"), 32)
    assert stub.Estimate(_request(at_limit), timeout=30).status == pb.EstimateResponse.OK


def test_headers_pillow_would_walk_byte_by_byte_are_refused(server, jpeg):
    stub, images = server
    calls = images.calls
    sos = jpeg.find(b"\xff\xda")
    for hostile in (jpeg[:sos] + b"\xff" * 7_000_000 + jpeg[sos:],  # fill bytes: 2.7 s in Pillow's marker loop
                    jpeg[:sos] + b"\x00" * 7_000_000 + jpeg[sos:],  # junk between segments
                    jpeg[:sos] + b"\xff\xfe\x00\x02" * 1_000_000 + jpeg[sos:]):  # a million empty comments
        with pytest.raises(grpc.RpcError) as err:
            stub.Estimate(_request(hostile), timeout=30)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "first scan" in err.value.details()
    assert images.calls == calls
    padded = jpeg[:sos] + b"\xff" * 1000 + jpeg[sos:]  # a few fill bytes are legal JPEG
    assert stub.Estimate(_request(padded), timeout=30).status == pb.EstimateResponse.OK


def test_repeated_fields_are_counted_before_anything_walks_them(server, jpeg):
    stub, _ = server
    many = [float("nan")] * 1_000_000  # 8 MB: walked (and a NaN formatted) they cost ~100 ms of the event loop
    distortion = pb.Intrinsics(fx=500, fy=500, cx=320, cy=240, width=640, height=480, distortion=many)
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(pb.EstimateRequest(estimator="images", intrinsics=distortion), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "got 1000000" in err.value.details() and "nan" not in err.value.details()
    prior = pb.PosePrior(pose=pb.Pose(qw=1.0, tz=0.5), covariance=pb.PoseCovariance(data=many))
    with pytest.raises(grpc.RpcError) as err:
        stub.Estimate(_request(jpeg, prior=prior), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "36 values" in err.value.details() and "got 1000000" in err.value.details()


# -- the metrics port ----------------------------------------------------------------------------------------

def _wait_for(condition, timeout_s: float = 20.0) -> None:
    """Wait until `condition()` holds (polled; the bound only stops a broken test from hanging)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.01)


def test_idle_metrics_connections_hold_no_thread_and_are_closed_when_idle_too_long(monkeypatch, capfd):
    monkeypatch.setattr(metrics, "METRICS_IDLE_S", 5.0)
    port = _free_port()
    with BackgroundServer(EstimatorRegistry([ImageEstimator()]), grace_s=0.0,
                          hardening=Hardening(metrics_port=port)) as srv:
        http = srv.running.metrics_http
        scrape = f"http://127.0.0.1:{port}/metrics"
        assert "flextrack_streams" in urllib.request.urlopen(scrape, timeout=30).read().decode()  # pool started
        threads = threading.active_count()
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(100)]
        _wait_for(lambda: http._held == 100)  # every one accepted and waiting for its request
        assert threading.active_count() - threads <= 20  # none of them holds a thread
        assert "flextrack_streams" in urllib.request.urlopen(scrape, timeout=30).read().decode()  # scrapes go on
        _wait_for(lambda: http._held == 0)  # closed after METRICS_IDLE_S without a request
        for s in idle:
            s.settimeout(10)
            assert s.recv(1) == b""  # the server closed it
            s.close()
        # clients that go away before their answer: no traceback (stderr is JSON lines)
        for _ in range(20):
            s = socket.create_connection(("127.0.0.1", port))
            s.sendall(b"GET /metrics HTTP/1.0\r\n\r\n")
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # reset, not a clean close
            s.close()
        _wait_for(lambda: http._held == 0)
    assert "Traceback" not in capfd.readouterr().err
