"""The nginx gate in front of a server (flextrack/loadtest/front_proxy.py, `flextrack bench capacity --front
nginx`): past its bound on open Track streams a new device gets RESOURCE_EXHAUSTED with a retry
pushback, from nginx itself; other calls pass through. The live test needs nginx and skips without it."""

from __future__ import annotations

import threading
import time

import grpc
import pytest

from flextrack.loadtest import front_proxy, servers
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc


def test_config_bounds_track_streams_and_answers_the_excess_as_grpc(tmp_path):
    text = front_proxy.render_config("127.0.0.1:5000", 6000, 7, tmp_path)
    assert "listen 127.0.0.1:6000 http2;" in text and "server 127.0.0.1:5000;" in text
    track = text.split(f"location {front_proxy.TRACK_PATH}")[1].split("}")[0]
    assert "limit_conn streams 7;" in track and "error_page 429 = @exhausted;" in track
    exhausted = text.split("location @exhausted")[1]
    assert "grpc-status 8" in exhausted and "grpc-retry-pushback-ms" in exhausted and "return 204;" in exhausted
    assert "limit_conn streams" not in front_proxy.render_config("127.0.0.1:5000", 6000, None, tmp_path)


def _no_frames(stop: threading.Event):
    """Sends nothing until `stop` (the test sets it when done): the stream stays open, as a device's does
    between frames, and no generator is left sleeping behind the test."""
    stop.wait(60)
    yield from ()


def _open_track(channel: grpc.Channel, stop: threading.Event):
    """A Track stream that sends nothing; its code once the server (or the gate) has answered it."""
    call = pb_grpc.PoseEstimationStub(channel).Track(_no_frames(stop), timeout=30.0)
    try:
        call.initial_metadata()
        return call, (call.code() if call.done() else None)
    except grpc.RpcError as exc:
        return call, exc.code()


@pytest.mark.skipif(front_proxy.nginx_binary() is None, reason="nginx is not installed (Debian: apt-get install nginx-light)")
def test_nginx_refuses_the_device_past_its_bound_and_passes_the_rest(tmp_path):
    server = servers.start_serve(["--log-level", "WARNING"])
    proxy = None
    channels: list[grpc.Channel] = []
    stop = threading.Event()
    try:
        proxy = front_proxy.start_nginx(server.address, 1, tmp_path / "nginx")
        channels = [grpc.insecure_channel(proxy.address) for _ in range(2)]
        first, code = _open_track(channels[0], stop)
        assert code is None  # admitted: the stream stays open
        second, code = _open_track(channels[1], stop)
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED
        pushback = dict(second.trailing_metadata() or ())
        assert 1000 <= int(pushback["grpc-retry-pushback-ms"]) <= 3000
        estimators = pb_grpc.PoseEstimationStub(channels[1]).ListEstimators(pb.ListEstimatorsRequest(), timeout=30)
        assert "gt_oracle" in {e.name for e in estimators.estimators}  # other calls are not bounded
        first.cancel()
        for _ in range(300):  # the slot frees once nginx has seen the first stream end (polled, 30 s at most)
            again, code = _open_track(channels[1], stop)
            again.cancel()
            if code is None:
                break
            time.sleep(0.1)
        assert code is None
    finally:
        stop.set()
        for channel in channels:
            channel.close()
        if proxy is not None:
            proxy.stop()
        server.stop()
