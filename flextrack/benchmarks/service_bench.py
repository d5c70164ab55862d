"""Service overhead: gt_oracle vs a no-op echo servicer, Track stream and unary Estimate, ~100 kB JPEGs.

Both servers run in child processes of this one (one process tree), the clients here on asyncio;
each stream or caller is closed-loop (the next frame goes once the last answer is back), and the
backends take turns in one-second slices. The ratio oracle/echo of frames/s says how much the
service itself (validation, oracle look-up, pose encoding) costs over bare gRPC transport; on a
busy machine the servers' CPU time per frame is the steadier measure of the same thing.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import multiprocessing
import os
import tempfile
import time
from pathlib import Path

import cv2
import grpc
import numpy as np

from flextrack import wire
from flextrack.geometry.camera import PinholeCamera
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

SLICE_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=10.0,
                        help="measuring time per (mode, backend) pair, in alternating 1 s slices")
    parser.add_argument("--payload-kb", type=float, default=100.0, help="JPEG size per request in kB")
    parser.add_argument("--streams", type=int, default=4, help="concurrent Track streams / unary callers")
    parser.add_argument("--warmup-s", type=float, default=1.0, help="unmeasured time before each measurement")


def make_jpeg(target_kb: float, width: int = 640, height: int = 480, seed: int = 0) -> bytes:
    """A noisy JPEG whose quality is chosen so that its size is closest to target_kb."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur((rng.random((height, width, 3)) * 255).astype(np.uint8), (3, 3), 0)
    encoded = [cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, q])[1].tobytes() for q in range(5, 101)]
    return min(encoded, key=lambda b: abs(len(b) - target_kb * 1000))


def _serve_child(backend: str, sequence_root: str, conn) -> None:
    """Child process: one server on a free loopback port; sends the port, runs until terminated."""
    if backend == "echo":
        from flextrack.benchmarks.echo_servicer import start_echo_server

        async def main():
            server, port = await start_echo_server()
            conn.send(port)
            await server.wait_for_termination()

        asyncio.run(main())
    else:  # exactly what `flextrack serve` runs
        from estimators.gt_oracle import GtOracleEstimator
        from estimators.registry import EstimatorRegistry
        from service.server import serve

        asyncio.run(serve(lambda: EstimatorRegistry([GtOracleEstimator(sequence_roots=[sequence_root])]),
                          host="127.0.0.1", port=0, on_serving=conn.send))


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc; NaN elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _requests(jpeg: bytes, times_ns: np.ndarray, sequence: str, count: int = 1000) -> list[pb.EstimateRequest]:
    cam = PinholeCamera.linemod()
    intrinsics = wire.intrinsics_to_pb(cam)
    image = pb.Image(encoding=pb.Image.JPEG, data=jpeg, width=cam.width, height=cam.height)
    return [pb.EstimateRequest(session_id="bench", frame_id=i, capture_time_ns=int(times_ns[i % len(times_ns)]),
                               sequence=sequence, image=image, intrinsics=intrinsics) for i in range(count)]


async def _slice(stub, mode: str, requests: list, seconds: float, streams: int) -> list[float]:
    """Latencies (s) of `streams` closed-loop workers for `seconds`."""
    latencies: list[float] = []
    t_end = time.perf_counter() + seconds

    async def worker(k: int):
        call = stub.Track() if mode == "track" else None
        i = k
        while time.perf_counter() < t_end:
            request = requests[i % len(requests)]
            sent = time.perf_counter()
            if call is not None:
                await call.write(request)
                response = await call.read()
            else:
                response = await stub.Estimate(request)
            if response.status != pb.EstimateResponse.OK:
                raise RuntimeError(f"{mode} frame {request.frame_id}: {response.message}")
            latencies.append(time.perf_counter() - sent)
            i += streams
        if call is not None:
            await call.done_writing()

    await asyncio.gather(*(worker(k) for k in range(streams)))
    return latencies


async def _compare(servers: dict[str, tuple[str, int]], mode: str, requests: list, args) -> dict[str, dict]:
    """Alternate one-second slices between the backends (name -> (address, pid)) so that load from
    elsewhere on the machine hits both alike; server CPU per frame is the figure least moved by it."""
    options = [("grpc.max_send_message_length", 8 << 20)]
    channels = {name: grpc.aio.insecure_channel(address, options=options) for name, (address, _) in servers.items()}
    stubs = {name: pb_grpc.PoseEstimationStub(channel) for name, channel in channels.items()}
    latencies: dict[str, list[float]] = {name: [] for name in servers}
    cpu_s = dict.fromkeys(servers, 0.0)
    slices = max(1, round(args.seconds / SLICE_S))
    try:
        for stub in stubs.values():
            await _slice(stub, mode, requests, args.warmup_s, args.streams)
        for _ in range(slices):
            for name, stub in stubs.items():
                before = _cpu_s(servers[name][1])
                latencies[name] += await _slice(stub, mode, requests, SLICE_S, args.streams)
                cpu_s[name] += _cpu_s(servers[name][1]) - before
    finally:
        for channel in channels.values():
            await channel.close()
    results = {}
    for name, values in latencies.items():
        ms = np.asarray(values) * 1e3
        results[name] = {"fps": len(ms) / (SLICE_S * slices), "p50": float(np.percentile(ms, 50)),
                         "p99": float(np.percentile(ms, 99)), "cpu_us": cpu_s[name] / len(ms) * 1e6}
    return results


def run(args: argparse.Namespace) -> int:
    from flextrack.testing.toy_sequence import write_orbit_sequence

    with tempfile.TemporaryDirectory() as tmp:
        seq = write_orbit_sequence(Path(tmp) / "orbit", frames=300)
        jpeg = make_jpeg(args.payload_kb)
        requests = _requests(jpeg, seq.frame_times_ns, seq.name)
        ctx = multiprocessing.get_context("spawn")
        children, servers = [], {}
        try:
            for backend in ("echo", "gt_oracle"):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_serve_child, args=(backend, str(seq.root), child), daemon=True)
                proc.start()
                children.append(proc)
                if not parent.poll(60):
                    raise RuntimeError(f"{backend} server did not start")
                servers[backend] = (f"127.0.0.1:{parent.recv()}", proc.pid)
            print(f"payload: {len(jpeg) / 1000:.1f} kB JPEG 640x480; {args.streams} closed-loop streams/callers; "
                  f"{args.seconds:g} s per row, in alternating {SLICE_S:g} s slices")
            print(f"{'mode':<7}{'backend':<11}{'frames/s':>10}{'p50 ms':>9}{'p99 ms':>9}{'server CPU us/frame':>21}")
            for mode in ("track", "unary"):
                result = asyncio.run(_compare(servers, mode, requests, args))
                for backend, r in result.items():
                    print(f"{mode:<7}{backend:<11}{r['fps']:>10.0f}{r['p50']:>9.2f}{r['p99']:>9.2f}{r['cpu_us']:>21.0f}")
                ratio = result["gt_oracle"]["fps"] / result["echo"]["fps"]
                cpu_ratio = result["echo"]["cpu_us"] / result["gt_oracle"]["cpu_us"]
                print(f"{mode:<7}ratio gt_oracle/echo frames/s: {ratio:.2f}; "
                      f"echo/gt_oracle server CPU per frame (the same ratio, server-bound): {cpu_ratio:.2f}")
        finally:
            for proc in children:
                proc.terminate()
                proc.join(10)
    return 0
