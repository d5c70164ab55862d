"""`flextrack serve` as a process: JSON logs, health check command, graceful stop on SIGTERM (exit 0)."""

import json
import signal
import subprocess
import sys
from pathlib import Path

import grpc

from flextrack.benchmarks.toy_sequence import write_orbit_sequence
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
                pb.EstimateRequest(capture_time_ns=int(seq.frame_times_ns[2])), timeout=5)
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
    for option in ("--port", "--config", "--host", "--max-message-mb", "--log-level", "--check", "--gil-switch-ms"):
        assert option in done.stdout


def test_serve_refuses_a_gil_switch_interval_that_is_not_positive():
    done = subprocess.run(check=False, args=[sys.executable, "-m", "flextrack", "serve", "--port", "0", "--gil-switch-ms", "0"],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--gil-switch-ms must be > 0" in done.stderr
