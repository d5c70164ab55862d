"""Property-based fuzzing of a real loopback server: thousands of random and malformed requests
(valid protobuf with wild values, and bytes that are not protobuf at all) through the same
interceptors the server runs with. The server must not crash, must never send an exception trace,
and every answer must be a defined status: a response status for the Track stream (one answer per
frame, in order) and a gRPC code for unary calls.

The classes an adversarial client found (issue 20) are in the mix: strings of up to 20,000
characters in every name (the answer keeps its code and a short message), unique names by the
hundred (the metrics page grows no series), decompression bombs (images whose header declares tens
of megapixels: refused before decoding) and calls cancelled at random moments (counted CANCELLED,
every admission slot given back). A `flextrack serve` process under the same kinds of frames, the
vision estimator decoding corrupt JPEG/PNG, keeps its log one JSON object a line."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import cv2
import grpc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimators.registry import EstimatorRegistry
from flextrack.loadtest.workload import synthetic
from flextrack.testing.toy_sequence import write_orbit_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.cli import DEFAULT_CONFIG
from service.hardening import Hardening
from service.limits import MAX_MESSAGE_CHARS
from service.server import BackgroundServer

TOKEN = "fuzz-token"
METADATA = (("authorization", f"Bearer {TOKEN}"),)
# Codes a unary call may fail with: each says what the caller did wrong or that it should retry.
DEFINED_CODES = {grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND, grpc.StatusCode.FAILED_PRECONDITION,
                 grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.UNAVAILABLE}
# The server's codes for a call: the defined ones, the client's own cancellation, and the metrics' outcome names.
COUNTED_CODES = {c.name for c in DEFINED_CODES} | {"CANCELLED", "DEADLINE_EXCEEDED"} | {
    pb.EstimateResponse.Status.Name(s) for s in pb.EstimateResponse.Status.values()}
REPO = Path(__file__).resolve().parent.parent
DEFINED_STATUSES = set(pb.EstimateResponse.Status.values()) - {pb.EstimateResponse.STATUS_UNSPECIFIED}
TRACE_MARKS = ("Traceback", 'File "', "Error(", ", line ")  # not bare "line ": pvnet's messages say "outline "


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    seq = write_orbit_sequence(tmp_path_factory.mktemp("seq") / "orbit", frames=20)
    registry = EstimatorRegistry.from_config(DEFAULT_CONFIG)
    registry.get("gt_oracle").add_sequence(seq.root)
    registry.get("gt_noisy").add_sequence(seq.root)
    hardening = Hardening(tokens=[TOKEN], max_queue=64)
    with BackgroundServer(registry, grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        yield channel, seq, hardening


def _no_trace(text: str) -> bool:
    return not any(mark in text for mark in TRACE_MARKS)


_finite_or_wild = st.one_of(st.floats(-1e4, 1e4), st.floats(allow_nan=True, allow_infinity=True))
_small_jpeg = pb.EstimateRequest.FromString(synthetic(0, frames=1).templates[0].body).image.data


def _chunk(kind: bytes, body: bytes) -> bytes:
    return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")


def _png_bomb(width: int, height: int) -> bytes:
    """A PNG header declaring width x height, then a short stream of zeros (the start of a bomb)."""
    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(bytes(1 << 20), 9))
            + _chunk(b"IEND", b""))


# Decompression bombs: a real 8000x6000 JPEG (a few hundred kB, 144 MB decoded) and PNG headers of 16-50 Mpx.
_BOMBS = [pb.Image(encoding=pb.Image.JPEG, data=cv2.imencode(".jpg", np.zeros((6000, 8000, 3), np.uint8))[1].tobytes(),
                   width=8000, height=6000),
          pb.Image(encoding=pb.Image.PNG, data=_png_bomb(5000, 5000), width=5000, height=5000),
          pb.Image(encoding=pb.Image.PNG, data=_png_bomb(50_000, 1000), width=640, height=480)]  # declared small
_long_strings = st.builds(lambda c, n: c * n, st.characters(codec="utf-8"), st.integers(129, 20_000))


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
        estimator=draw(st.one_of(st.sampled_from(["", "gt_oracle", "gt_noisy", "pnp"]), st.text(max_size=10),
                                 _long_strings)),
        object_id=draw(st.one_of(st.sampled_from(["", "toy", "default"]), st.text(max_size=10), _long_strings)),
        sequence=draw(st.one_of(st.sampled_from(["", "orbit"]), st.text(max_size=10), _long_strings)),
        image=draw(st.one_of(st.just(pb.Image()), images(), st.sampled_from(_BOMBS))),
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
    channel, seq, _ = server
    stub = pb_grpc.PoseEstimationStub(channel)

    @_fuzz_settings(200)
    @given(st.lists(requests(seq), min_size=1, max_size=25))
    def check(batch):
        answers = list(stub.Track(iter(batch), timeout=30, metadata=METADATA))
        assert [a.frame_id for a in answers] == [r.frame_id for r in batch]
        for answer in answers:
            assert answer.status in DEFINED_STATUSES
            assert _no_trace(answer.message), answer.message
            assert len(answer.message) <= MAX_MESSAGE_CHARS
            if answer.status == pb.EstimateResponse.OK:
                q = [answer.pose.qw, answer.pose.qx, answer.pose.qy, answer.pose.qz]
                assert np.isclose(np.linalg.norm(q), 1.0) and np.isfinite(answer.pose.tz)

    check()


def test_estimate_fails_only_with_defined_codes_and_no_trace(server):
    channel, seq, _ = server
    stub = pb_grpc.PoseEstimationStub(channel)

    @_fuzz_settings(400)
    @given(requests(seq))
    def check(request):
        try:
            answer = stub.Estimate(request, timeout=30, metadata=METADATA)
        except grpc.RpcError as exc:
            assert exc.code() in DEFINED_CODES, (exc.code(), (exc.details() or "")[:300])
            assert _no_trace(exc.details() or ""), exc.details()
            assert len(exc.details() or "") <= MAX_MESSAGE_CHARS
        else:
            assert answer.status in DEFINED_STATUSES and _no_trace(answer.message)

    check()


def test_bytes_that_are_not_protobuf_are_refused_cleanly(server):
    channel, _, _ = server
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


def _series(metrics) -> set[str]:
    return {f"{s.name}{sorted(s.labels.items())}" for m in metrics.registry.collect() for s in m.samples}


def test_unique_names_grow_no_metrics_series(server):
    channel, _, hardening = server
    stub = pb_grpc.PoseEstimationStub(channel)
    with pytest.raises(grpc.RpcError):  # the one series unknown names share
        stub.Estimate(pb.EstimateRequest(estimator="never-registered"), timeout=10, metadata=METADATA)
    before = _series(hardening.metrics)

    @_fuzz_settings(100)
    @given(st.lists(st.text(min_size=1, max_size=200), min_size=1, max_size=10, unique=True))
    def check(names):
        requests = [pb.EstimateRequest(frame_id=i, estimator=f"unknown:{name}") for i, name in enumerate(names)]
        answers = list(stub.Track(iter(requests), timeout=30, metadata=METADATA))
        assert all(a.status == pb.EstimateResponse.INVALID_INPUT for a in answers)

    check()
    assert _series(hardening.metrics) == before


def _wait_for(condition, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.01)


def test_cancelled_calls_are_counted_and_give_their_slots_back(server):
    channel, seq, hardening = server
    stub = pb_grpc.PoseEstimationStub(channel)
    metrics = hardening.metrics

    def outcomes() -> set[str]:
        return {s.labels["code"] for m in metrics.registry.collect() for s in m.samples
                if s.name == "flextrack_requests_total"}

    @_fuzz_settings(60)
    @given(st.lists(requests(seq), min_size=1, max_size=8), st.lists(st.integers(0, 3), min_size=1, max_size=8),
           st.booleans())
    def check(batch, waits_ms, stream):
        if stream:  # a Track stream cancelled after some of its answers (maybe none)
            call = stub.Track(iter(batch), timeout=30, metadata=METADATA)
            for _ in range(waits_ms[0]):
                try:
                    next(call)
                except (StopIteration, grpc.RpcError):
                    break
            call.cancel()
        else:  # unary calls cancelled at once or after a few ms
            calls = [stub.Estimate.future(r, timeout=30, metadata=METADATA) for r in batch]
            for call, wait in zip(calls, waits_ms * len(calls)):
                threading.Event().wait(wait / 1e3)
                call.cancel()
            for call in calls:
                if not call.cancelled():
                    try:
                        call.result()
                    except grpc.RpcError as exc:
                        assert exc.code() in DEFINED_CODES | {grpc.StatusCode.CANCELLED}, exc.code()

    check()
    admission = hardening.admission
    _wait_for(lambda: all(depth == 0 for depth in admission._depth.values()) and admission.streams == 0)
    assert outcomes() <= COUNTED_CODES and "INTERNAL" not in outcomes()
    reply = stub.Estimate(pb.EstimateRequest(capture_time_ns=int(seq.frame_times_ns[3]), sequence="orbit"),
                          timeout=10, metadata=METADATA)
    assert reply.status == pb.EstimateResponse.OK  # still serving


def _vision_frames():
    """Frames for the vision estimator: mostly corrupt or bomb JPEG/PNG, that libjpeg/libpng would complain of."""
    rng = np.random.default_rng(0)
    png = cv2.imencode(".png", rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))[1].tobytes()
    jpeg = _small_jpeg
    frames = [(pb.Image.JPEG, jpeg[:-2] + bytes(40) + jpeg[-2:]),  # extraneous bytes: decodes, libjpeg warns
              (pb.Image.JPEG, jpeg[:len(jpeg) // 2]),  # truncated
              (pb.Image.PNG, png[:60] + bytes(30) + png[90:]),  # bad IDAT check: libpng prints an error
              (pb.Image.PNG, png[:len(png) // 3])]
    for _ in range(4):
        flipped = bytearray(jpeg)
        for i in rng.integers(400, len(jpeg), 8):
            flipped[i] = int(rng.integers(0, 256))
        frames.append((pb.Image.JPEG, bytes(flipped)))
    return [pb.Image(encoding=e, data=d, width=640, height=480) for e, d in frames] + _BOMBS


def test_the_server_log_stays_json_lines_under_fuzzing(tmp_path):
    config = tmp_path / "vision.toml"
    # the oracles, pnp and pvnet of the default config (the region estimators need a prior)
    config.write_text(DEFAULT_CONFIG.read_text().split("# Prior-guided refinement")[0])
    proc = subprocess.Popen([sys.executable, "-m", "flextrack", "serve", "--port", "0", "--config", str(config),
                             "--drain-s", "0", "--grace-s", "0"], cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        first = json.loads(proc.stderr.readline())
        assert first["msg"] == "listening"
        lines = [proc.stderr.readline()]
        while json.loads(lines[-1])["msg"] != "serving":  # each line JSON while it loads
            lines.append(proc.stderr.readline())
        intrinsics = pb.Intrinsics(fx=570, fy=570, cx=320, cy=240, width=640, height=480)
        frames = _vision_frames()
        with grpc.insecure_channel(first["address"]) as channel:
            stub = pb_grpc.PoseEstimationStub(channel)

            @_fuzz_settings(40)
            @given(st.lists(st.tuples(st.sampled_from(range(len(frames))), st.sampled_from(["pvnet", "pnp", "x" * 500])),
                            min_size=1, max_size=4))
            def check(picks):
                batch = [pb.EstimateRequest(frame_id=k, estimator=name, image=frames[i], intrinsics=intrinsics)
                         for k, (i, name) in enumerate(picks)]
                answers = list(stub.Track(iter(batch), timeout=60))
                assert [a.frame_id for a in answers] == [r.frame_id for r in batch]
                assert all(a.status in DEFINED_STATUSES and _no_trace(a.message) for a in answers)

            check()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        lines += proc.stderr.read().splitlines()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    records = []
    for line in lines:
        line = line.strip()
        if line:
            records.append(json.loads(line))  # fails on any line that is not one JSON object
    assert all(isinstance(r, dict) and {"ts", "level", "msg"} <= set(r) for r in records)
    assert records[-1]["msg"] == "stopped"
