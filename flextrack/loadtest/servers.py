"""Server processes for benchmarks: `flextrack serve` (as deployed) or a no-op echo servicer, each in a
child process of its own (a server that shared the load generator's process would share its GIL)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

ECHO_MAIN = """
import asyncio, sys
from flextrack.benchmarks.echo_servicer import start_echo_server
async def main():
    server, _ = await start_echo_server("127.0.0.1", int(sys.argv[1]))
    await server.wait_for_termination()
asyncio.run(main())
"""


def free_port() -> int:
    """A port free right now on loopback (the OS may hand it out again; fine for a benchmark)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class ServerProcess:
    name: str
    address: str
    process: subprocess.Popen

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM (a graceful stop for `flextrack serve`), then SIGKILL if it lingers; its exit code."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode


def parse_cpus(text: str | None) -> set[int] | None:
    """"0" or "1,2" -> a CPU set; None or "" -> None (no pinning). ValueError for CPUs this machine lacks."""
    if not text:
        return None
    cpus = {int(c) for c in text.split(",") if c.strip()}
    missing = cpus - os.sched_getaffinity(0)
    if missing:
        raise ValueError(f"CPUs {sorted(missing)} are not available here (have {sorted(os.sched_getaffinity(0))})")
    return cpus


def pin(pid: int, cpus: set[int] | None) -> None:
    """Restrict every thread of process `pid` (0: this one) to `cpus` (Linux), so that a server and its
    load generator do not take turns on the same cores; threads started later inherit it."""
    if not cpus:
        return
    for tid in os.listdir(f"/proc/{pid or os.getpid()}/task"):
        os.sched_setaffinity(int(tid), cpus)


def wait_serving(address: str, timeout_s: float = 60.0, process: subprocess.Popen | None = None) -> None:
    """Block until the gRPC health service at `address` says SERVING.

    The polling channel retries its connection every 0.1 s: with gRPC's default reconnect backoff
    (1 s, growing) it noticed a restarted server up to a second late, after clients had already
    reconnected to it."""
    deadline = time.monotonic() + timeout_s
    fast_reconnect = [(f"grpc.{k}_reconnect_backoff_ms", 100) for k in ("initial", "min", "max")]
    with grpc.insecure_channel(address, options=fast_reconnect) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while time.monotonic() < deadline:
            if process is not None and process.poll() is not None:
                raise RuntimeError(f"server at {address} exited with code {process.returncode} before serving")
            try:
                if stub.Check(health_pb2.HealthCheckRequest(), timeout=1).status == \
                        health_pb2.HealthCheckResponse.SERVING:
                    return
            except grpc.RpcError:
                pass
            time.sleep(0.1)
    raise TimeoutError(f"server at {address} was not SERVING after {timeout_s:g} s")


def start_serve(serve_args: list[str], name: str = "flextrack", port: int | None = None,
                log_path: Path | None = None, cpus: set[int] | None = None) -> ServerProcess:
    """`flextrack serve --host 127.0.0.1 --port P --drain-s 0 ARGS...` in a child process, returned once SERVING
    (and pinned to `cpus`, when given). No drain on SIGTERM: nothing balances load away from a benchmark's server
    (ARGS may still give one)."""
    port = port or free_port()
    address = f"127.0.0.1:{port}"
    command = [sys.executable, "-m", "flextrack", "serve", "--host", "127.0.0.1", "--port", str(port),
               "--drain-s", "0", *serve_args]
    if log_path:
        with open(log_path, "ab") as log:  # the child keeps its own copy of the file descriptor
            process = subprocess.Popen(command, stdout=log, stderr=log)
    else:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    server = ServerProcess(name, address, process)
    try:
        pin(process.pid, cpus)
        wait_serving(address, process=process)
    except BaseException:
        server.stop()
        raise
    return server


def start_echo(port: int | None = None, cpus: set[int] | None = None) -> ServerProcess:
    """The no-op echo servicer in a child process (it has no health service: wait for ListEstimators)."""
    port = port or free_port()
    address = f"127.0.0.1:{port}"
    process = subprocess.Popen([sys.executable, "-c", ECHO_MAIN, str(port)])
    pin(process.pid, cpus)
    from flextrack.v1 import pose_estimation_pb2 as pb
    from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

    with grpc.insecure_channel(address) as channel:
        try:
            pb_grpc.PoseEstimationStub(channel).ListEstimators(pb.ListEstimatorsRequest(), timeout=30,
                                                               wait_for_ready=True)
        except grpc.RpcError:
            process.kill()
            raise
    return ServerProcess("echo", address, process)
