"""`flextrack serve` as a process: JSON logs, health check command, graceful stop on SIGTERM (exit 0)."""

import json
import signal
import subprocess
import sys
from pathlib import Path

import grpc

from flextrack.testing.toy_sequence import write_orbit_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service import cli

REPO = Path(__file__).resolve().parent.parent


def test_serve_answers_then_stops_gracefully_on_sigterm(tmp_path):
    seq = write_orbit_sequence(tmp_path / "seqs" / "orbit", frames=5)
    config = tmp_path / "server.toml"
    config.write_text('[[estimators]]\nname = "gt"\nkind = "gt_oracle"\n[estimators.params]\nsequence_roots = ["seqs"]\n')
    proc = subprocess.Popen([sys.executable, "-m", "flextrack", "serve", "--host", "127.0.0.1", "--port", "0",
                             "--config", str(config), "--grace-s", "2"], cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        first = json.loads(proc.stderr.readline())  # the "listening" line names the port the OS chose
        assert first["msg"] == "listening"
        address = first["address"]
        assert json.loads(proc.stderr.readline())["msg"] == "serving"
        assert cli.check(address) == 0
        with grpc.insecure_channel(address) as channel:
            reply = pb_grpc.PoseEstimationStub(channel).Estimate(
                pb.EstimateRequest(capture_time_ns=int(seq.frame_times_ns[2])), timeout=30)
        assert reply.status == pb.EstimateResponse.OK
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        messages = [json.loads(line)["msg"] for line in proc.stderr.read().splitlines()]
        assert messages[-2:] == ["shutting down", "stopped"]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_check_fails_when_nothing_listens():
    assert cli.check("127.0.0.1:1", timeout_s=1.0) == 1


def test_serve_reports_a_bad_config_and_exits_nonzero(tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text('[[estimators]]\nkind = "nope"\n')
    done = subprocess.run(check=False, args=[sys.executable, "-m", "flextrack", "serve", "--port", "0", "--host", "127.0.0.1",
                           "--config", str(config)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "unknown kind 'nope'" in done.stderr and "Traceback" not in done.stderr


def test_serve_help_lists_its_options():
    done = subprocess.run(check=False, args=[sys.executable, "-m", "flextrack", "serve", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0
    for option in ("--port", "--config", "--host", "--max-message-mb", "--log-level", "--check", "--gil-switch-ms",
                   "--insecure-public", "--drain-s", "--metrics-host", "--max-image-pixels", "--max-name-chars",
                   "--max-keypoints"):
        assert option in done.stdout


def test_serve_refuses_a_gil_switch_interval_that_is_not_positive():
    done = subprocess.run(check=False, args=[sys.executable, "-m", "flextrack", "serve", "--port", "0", "--gil-switch-ms", "0"],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--gil-switch-ms must be > 0" in done.stderr


def _oracle_config(tmp_path) -> tuple[Path, object]:
    seq = write_orbit_sequence(tmp_path / "seqs" / "orbit", frames=5)
    config = tmp_path / "server.toml"
    config.write_text('[[estimators]]\nname = "gt"\nkind = "gt_oracle"\n[estimators.params]\nsequence_roots = ["seqs"]\n')
    return config, seq


def _start(config, *flags) -> tuple[subprocess.Popen, str]:
    """`flextrack serve` on a free loopback port, SERVING; returns the process and its address."""
    proc = subprocess.Popen([sys.executable, "-m", "flextrack", "serve", "--port", "0", "--config", str(config),
                             *flags], cwd=REPO, stderr=subprocess.PIPE, text=True)
    first = json.loads(proc.stderr.readline())
    assert first["msg"] == "listening", first
    assert json.loads(proc.stderr.readline())["msg"] == "serving"
    return proc, first["address"]


def _health(address: str) -> int:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(address) as channel:
        return health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="flextrack.v1.PoseEstimation"), timeout=30).status


def test_sigterm_drains_not_serving_while_still_answering_then_a_second_signal_stops(tmp_path):
    from grpc_health.v1 import health_pb2

    config, seq = _oracle_config(tmp_path)
    proc, address = _start(config, "--drain-s", "120", "--grace-s", "1")
    try:
        assert address.startswith("127.0.0.1:")  # the default bind is loopback
        assert _health(address) == health_pb2.HealthCheckResponse.SERVING
        proc.send_signal(signal.SIGTERM)
        assert json.loads(proc.stderr.readline())["msg"] == "draining"  # logged once health says NOT_SERVING
        assert _health(address) == health_pb2.HealthCheckResponse.NOT_SERVING  # the probe fails first...
        with grpc.insecure_channel(address) as channel:  # ...while calls are still served
            reply = pb_grpc.PoseEstimationStub(channel).Estimate(
                pb.EstimateRequest(capture_time_ns=int(seq.frame_times_ns[2])), timeout=30)
        assert reply.status == pb.EstimateResponse.OK
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)  # a second signal ends the 120 s drain
        assert proc.wait(timeout=20) == 0
        records = [json.loads(line) for line in proc.stderr.read().splitlines()]
        assert [r["msg"] for r in records][-2:] == ["shutting down", "stopped"]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_serve_on_a_taken_port_exits_nonzero_with_one_line(tmp_path):
    config, _ = _oracle_config(tmp_path)
    first, address = _start(config)  # another flextrack server (gRPC would have shared the port: SO_REUSEPORT)
    try:
        port = address.rsplit(":", 1)[1]
        done = subprocess.run([sys.executable, "-m", "flextrack", "serve", "--port", port, "--config", str(config)],
                              cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
        assert done.returncode == 1
        assert len(done.stderr.splitlines()) == 1 and "port is in use" in done.stderr, done.stderr
        assert cli.check(address) == 0  # the first one is untouched
    finally:
        first.terminate()
        first.wait(timeout=30)
    import socket

    with socket.socket() as other:  # a port held by another program
        other.bind(("127.0.0.1", 0))
        other.listen()
        done = subprocess.run([sys.executable, "-m", "flextrack", "serve", "--port", str(other.getsockname()[1]),
                               "--config", str(config)], cwd=REPO, capture_output=True, text=True, timeout=60,
                              check=False)
    assert done.returncode == 1 and len(done.stderr.splitlines()) == 1 and "Traceback" not in done.stderr


def test_default_bind_is_loopback_and_a_public_one_needs_auth_or_a_deliberate_flag(tmp_path):
    import argparse

    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    assert parser.parse_args([]).host == "127.0.0.1"
    assert cli.is_loopback("127.0.0.1") and cli.is_loopback("::1") and cli.is_loopback("localhost")
    assert not cli.is_loopback("0.0.0.0") and not cli.is_loopback("::") and not cli.is_loopback("example.org")
    config, _ = _oracle_config(tmp_path)
    done = subprocess.run([sys.executable, "-m", "flextrack", "serve", "--host", "0.0.0.0", "--port", "0",
                           "--config", str(config)], cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and "--insecure-public" in done.stderr
