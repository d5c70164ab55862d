"""A lone device timing its own refusals: `python -m flextrack.benchmarks.refusal_probe ADDRESS SECONDS [INTERVAL_S]`.

Why: in an overload run the load generator's one event loop drives hundreds of streams, so the
refusal times it records include its own queueing. This probe, a separate process that does
nothing else, opens a `Track` stream every INTERVAL_S, waits for the server's answer to it
(initial metadata when admitted, RESOURCE_EXHAUSTED when refused), closes it and prints one JSON
line: the refusal times in ms and the count of streams admitted. It ignores the server's retry
pushback on purpose: it times refusals, it is not a patient device.
"""

from __future__ import annotations

import json
import sys
import time

import grpc

from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc


def probe(address: str, seconds: float, interval_s: float = 0.1) -> dict:
    refused_ms, admitted, other = [], 0, {}
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.PoseEstimationStub(channel)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            started = time.perf_counter()
            call = stub.Track(iter(()), timeout=5.0)  # no frames: the server's answer to the stream itself
            try:
                call.initial_metadata()
                code = call.code() if call.done() else None
            except grpc.RpcError as exc:
                code = exc.code()
            elapsed_ms = (time.perf_counter() - started) * 1e3
            if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
                refused_ms.append(elapsed_ms)
            elif code is None or code == grpc.StatusCode.OK:
                admitted += 1
            else:
                other[code.name] = other.get(code.name, 0) + 1
            call.cancel()
            time.sleep(interval_s)
    return {"refused_ms": refused_ms, "admitted": admitted, "other": other}


if __name__ == "__main__":
    print(json.dumps(probe(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 0.1)))
