"""What an adversarial client found (issue 20), each on a real loopback server: long strings keep their codes,
unknown names do not grow the metrics page, decompression bombs are refused before decoding, cancelled calls are
counted and keep their admission slot until their worker is done, /metrics only on its configured address."""

from __future__ import annotations

import re
import socket
import threading
import time
import urllib.error
import urllib.request
import zlib

import cv2
import grpc
import numpy as np
import pytest
import trimesh

from estimators.base import EstimateInput, EstimateOutput, Estimator, Status
from estimators.objects import ObjectRegistry, load_object
from estimators.pnp import PnpEstimator
from estimators.registry import EstimatorRegistry
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service import request_decoding
from service.hardening import Hardening
from service.limits import DEFAULT_MAX_IMAGE_PIXELS, MAX_MESSAGE_CHARS, RequestLimits, clip_message, echo
from service.server import BackgroundServer

TRAILER_BYTES = 8 * 1024  # gRPC's default limit on the trailers that carry an error's details


class ImageEstimator(Estimator):
    """Decodes the image (uses_image) and counts the frames it was given."""

    kind, version, uses_image = "images", "1", True

    def __init__(self):
        super().__init__("images", ["obj"])
        self.calls, self._lock = 0, threading.Lock()  # worker threads count concurrently

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        with self._lock:
            self.calls += 1
        return EstimateOutput(Status.OK, np.eye(4), 1.0)


class GatedEstimator(Estimator):
    """Works on a frame until the test opens its gate (a thread that cannot be stopped, as a network's)."""

    kind, version = "gated", "1"

    def __init__(self):
        super().__init__("gated", ["obj"])
        self.gate, self.started = threading.Event(), threading.Event()
        self.in_progress = self.most_in_progress = 0
        self._lock = threading.Lock()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        with self._lock:
            self.in_progress += 1
            self.most_in_progress = max(self.most_in_progress, self.in_progress)
        self.started.set()
        self.gate.wait(30)
        with self._lock:
            self.in_progress -= 1
        return EstimateOutput(Status.OK, np.eye(4), 1.0)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("objects")
    trimesh.creation.box(extents=(90.0, 50.0, 30.0)).export(root / "box.ply")
    objects = ObjectRegistry([load_object("box", root / "box.ply")])
    images = ImageEstimator()
    hardening = Hardening()
    registry = EstimatorRegistry([PnpEstimator(objects), images], objects=objects)
    with BackgroundServer(registry, grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        yield pb_grpc.PoseEstimationStub(channel), hardening, images


def _rpc_error(call, *args, **kw) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        call(*args, timeout=10, **kw)
    return err.value


# -- 1. long strings keep their codes ----------------------------------------------------------------

LONG = "A" * 16_000
LONG_STRINGS = [
    ("estimator", {"estimator": LONG}, grpc.StatusCode.NOT_FOUND),
    ("object_id", {"estimator": "pnp", "object_id": LONG}, grpc.StatusCode.NOT_FOUND),
    ("sequence", {"estimator": "pnp", "sequence": LONG}, grpc.StatusCode.FAILED_PRECONDITION),
    ("session_id", {"estimator": "pnp", "session_id": LONG}, grpc.StatusCode.INVALID_ARGUMENT),
]


@pytest.mark.parametrize("field, fields, code", LONG_STRINGS, ids=[c[0] for c in LONG_STRINGS])
def test_a_16_kb_string_keeps_its_code_and_a_short_message(server, field, fields, code):
    stub, _, _ = server
    err = _rpc_error(stub.Estimate, pb.EstimateRequest(**fields))
    assert err.code() == code, (err.code(), err.details()[:200])
    assert len(err.details()) <= MAX_MESSAGE_CHARS and "128 characters" in err.details()


def test_ten_thousand_unknown_keypoint_ids_and_a_huge_name_in_a_stream(server):
    stub, _, _ = server
    many = [pb.Keypoint(id=100_000 + i, u=1.0, v=2.0) for i in range(10_000)]
    err = _rpc_error(stub.Estimate, pb.EstimateRequest(estimator="pnp", keypoints=many))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "at most 1024" in err.details()
    # under the keypoint bound, every id unknown: the estimator's message lists them, cut to fit
    some = [pb.Keypoint(id=100_000 + i, u=1.0, v=2.0) for i in range(1000)]
    intrinsics = pb.Intrinsics(fx=500, fy=500, cx=320, cy=240, width=640, height=480)
    err = _rpc_error(stub.Estimate, pb.EstimateRequest(estimator="pnp", keypoints=some, intrinsics=intrinsics))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and len(err.details()) <= MAX_MESSAGE_CHARS
    # a 7.9 MB name in a Track stream: answered in the stream with a short message, the stream goes on
    answers = list(stub.Track(iter([pb.EstimateRequest(frame_id=1, estimator="B" * 7_900_000),
                                    pb.EstimateRequest(frame_id=2, estimator="pnp", object_id=LONG)]), timeout=30))
    assert [a.frame_id for a in answers] == [1, 2]
    assert all(a.status == pb.EstimateResponse.INVALID_INPUT and a.ByteSize() < 2 * MAX_MESSAGE_CHARS
               for a in answers)


def test_messages_are_clipped_and_echoes_cut():
    assert clip_message("x" * 10) == "x" * 10
    long = "head " + "y" * 100_000 + " tail"
    clipped = clip_message(long)
    assert len(clipped) <= MAX_MESSAGE_CHARS and clipped.startswith("head ") and clipped.endswith(" tail")
    assert echo("abc") == "'abc'" and echo("z" * 1000).endswith("... (1000 characters)") and len(echo("z" * 1000)) < 80
    with pytest.raises(ValueError, match="max-keypoints"):
        RequestLimits(max_keypoints=3)


# -- 2. unknown names do not grow the metrics page -------------------------------------------------------

def _series(metrics) -> set[str]:
    return {f"{s.name}{sorted(s.labels.items())}" for m in metrics.registry.collect() for s in m.samples}


def test_a_thousand_unknown_names_leave_the_metrics_page_the_same_size(server):
    stub, hardening, _ = server
    from prometheus_client import generate_latest

    _rpc_error(stub.Estimate, pb.EstimateRequest(estimator="warm-up"))
    # the server counts a call just after its answer went out: wait until it has, then the "(unknown)" series exist
    _wait_for(lambda: hardening.metrics.count("NOT_FOUND", "Estimate", "(unknown)") >= 1)
    before, size_before = _series(hardening.metrics), len(generate_latest(hardening.metrics.registry))
    for i in range(1000):
        _rpc_error(stub.Estimate, pb.EstimateRequest(estimator=f"name-{i}-" + "n" * 100))
    _wait_for(lambda: hardening.metrics.count("NOT_FOUND", "Estimate", "(unknown)") >= 1001)
    after, size_after = _series(hardening.metrics), len(generate_latest(hardening.metrics.registry))
    assert after == before  # no new series (label sets): only counts changed
    assert abs(size_after - size_before) < 200  # a few digits more in the counts and latency sums
    assert "name-" not in generate_latest(hardening.metrics.registry).decode()
    assert set(hardening.admission._depth) <= {"pnp", "images", "(unknown)"}  # queue depths keyed the same way


# -- 3. decompression bombs --------------------------------------------------------------------------------

def _png_bomb(width: int, height: int) -> bytes:
    """A grey PNG of width x height zeros, compressed (a few hundred kB for 100 Mpx)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    packer, row, idat = zlib.compressobj(9), bytes(width + 1), []
    for _ in range(height):
        idat.append(packer.compress(row))
    idat.append(packer.flush())
    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", b"".join(idat)) + chunk(b"IEND", b"")


def _peak_rss_kb() -> int:
    return int(re.search(r"VmHWM:\s+(\d+)", open("/proc/self/status").read()).group(1))


def test_decompression_bombs_are_refused_from_the_header_fast_and_without_memory(server, monkeypatch):
    stub, _, images = server
    jpeg = cv2.imencode(".jpg", np.zeros((6000, 8000, 3), np.uint8))[1].tobytes()  # 144 MB decoded
    png = _png_bomb(10_000, 10_000)  # 100 MB decoded (300 MB as RGB)
    bombs = [pb.Image(encoding=pb.Image.JPEG, data=jpeg, width=8000, height=6000),
             pb.Image(encoding=pb.Image.PNG, data=png, width=10_000, height=10_000),
             # declared small, the header says huge: refused from the header too
             pb.Image(encoding=pb.Image.PNG, data=png, width=640, height=480)]
    decodes = []
    monkeypatch.setattr(request_decoding, "_decode_rgb", lambda *a: decodes.append(a) or np.zeros((1, 1, 3)))
    calls_before = images.calls
    with open("/proc/self/clear_refs", "w") as f:  # reset this process's (the server's) peak RSS
        f.write("5")
    peak_before = _peak_rss_kb()
    for image in bombs:  # refused from the header: no decode (checked below), whatever the machine's speed
        err = _rpc_error(stub.Estimate, pb.EstimateRequest(estimator="images", image=image))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert str(DEFAULT_MAX_IMAGE_PIXELS) in err.details() or "but is 10000x10000" in err.details()
    assert not decodes and images.calls == calls_before  # nothing was decoded, no estimator ran
    assert _peak_rss_kb() - peak_before < 40_000  # the peak grew less than 40 MB (a decode: 144-300 MB)


def test_an_image_at_the_limit_is_decoded_and_one_pixel_more_is_not():
    limits = RequestLimits(max_image_pixels=64 * 48)
    ok = pb.EstimateRequest(image=pb.Image(encoding=pb.Image.JPEG, width=64, height=48))
    limits.check(ok)
    with pytest.raises(Exception, match="limit of 3072 pixels"):
        limits.check(pb.EstimateRequest(image=pb.Image(encoding=pb.Image.JPEG, width=65, height=48)))


# -- 4. cancellations ---------------------------------------------------------------------------------------

def _wait_for(condition, timeout_s: float = 10.0) -> None:
    """Wait until `condition()` holds (polled; the bound only stops a broken test from hanging)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.005)


@pytest.mark.parametrize("rpc", ["estimate", "track"])
def test_a_cancelled_call_is_counted_cancelled_and_holds_its_slot_until_its_work_ends(rpc):
    estimator, hardening = GatedEstimator(), Hardening(max_queue=1)
    with BackgroundServer(EstimatorRegistry([estimator]), grace_s=0.0, workers=4, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        stub, servicer = pb_grpc.PoseEstimationStub(channel), srv.running.servicer
        if rpc == "estimate":
            call = stub.Estimate.future(pb.EstimateRequest(frame_id=1), timeout=30)
        else:
            call = stub.Track(iter([pb.EstimateRequest(frame_id=1)]), timeout=30)
        assert estimator.started.wait(10)
        call.cancel()
        _wait_for(lambda: servicer.running_after_cancel == 1)  # the server saw the cancel; the thread still works
        # the slot is still taken by the thread that runs: the next frame is refused, not queued behind it
        err = _rpc_error(stub.Estimate, pb.EstimateRequest(frame_id=2))
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        [answer] = list(stub.Track(iter([pb.EstimateRequest(frame_id=3)]), timeout=10))
        assert answer.status == pb.EstimateResponse.UNAVAILABLE
        assert hardening.admission.depth("gated") == 1
        estimator.gate.set()  # the work ends: the slot is free, the cancellation counted as such
        _wait_for(lambda: hardening.metrics.count("CANCELLED", estimator="gated") == 1)
        assert hardening.admission.depth("gated") == 0 and servicer.running_after_cancel == 0
        assert stub.Estimate(pb.EstimateRequest(frame_id=4), timeout=10).status == pb.EstimateResponse.OK
    assert estimator.most_in_progress == 1  # the bound held throughout
    assert hardening.metrics.count("INTERNAL") == 0


# -- 5. the metrics endpoint -------------------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_metrics_listen_on_the_configured_address_and_serve_only_metrics():
    assert Hardening().metrics_host == "127.0.0.1"  # loopback unless the operator says otherwise
    port = _free_port()
    hardening = Hardening(metrics_port=port, metrics_host="127.0.0.1")
    with BackgroundServer(EstimatorRegistry([ImageEstimator()]), grace_s=0.0, hardening=hardening) as srv:
        http = srv.running.metrics_http
        assert http.server_address == ("127.0.0.1", port)
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=30).read().decode()
        assert "flextrack_streams" in page
        for path in ("/", "/anything", "/metrics/../x"):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30)
            assert err.value.code == 404


def test_a_taken_metrics_port_stops_serve_with_one_line():
    import subprocess
    import sys
    from pathlib import Path

    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        done = subprocess.run([sys.executable, "-m", "flextrack", "serve", "--port", "0", "--metrics-port",
                               str(other.getsockname()[1])], cwd=Path(__file__).resolve().parent.parent,
                              capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1 and done.stderr.splitlines() == [done.stderr.strip()], done.stderr
    assert "cannot serve /metrics" in done.stderr


def test_metrics_auth_takes_the_servers_token_and_tls(tmp_path):
    trustme = pytest.importorskip("trustme", reason="trustme (dev extra) makes the test certificates")
    import ssl

    ca = trustme.CA()
    leaf = ca.issue_cert("127.0.0.1")
    cert, key = tmp_path / "server.pem", tmp_path / "server.key"
    leaf.cert_chain_pems[0].write_to_path(cert)
    leaf.private_key_pem.write_to_path(key)
    with pytest.raises(ValueError, match="--metrics-auth needs"):
        Hardening(metrics_auth=True)
    port = _free_port()
    hardening = Hardening(tls_cert=cert, tls_key=key, tokens=["metrics-token"], metrics_port=port, metrics_auth=True)
    context = ssl.create_default_context()
    ca.configure_trust(context)
    url = f"https://127.0.0.1:{port}/metrics"
    with BackgroundServer(EstimatorRegistry([ImageEstimator()]), grace_s=0.0, hardening=hardening):
        for header in (None, "Bearer wrong", "metrics-token"):
            request = urllib.request.Request(url, headers={"Authorization": header} if header else {})
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(request, timeout=30, context=context)
            assert err.value.code == 401
        request = urllib.request.Request(url, headers={"Authorization": "Bearer metrics-token"})
        assert b"flextrack_streams" in urllib.request.urlopen(request, timeout=30, context=context).read()
        with pytest.raises(OSError):  # plain HTTP is not served (reset or refused)
            urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=30)
