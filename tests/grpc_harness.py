"""A real loopback server for the security, load and fuzz tests: S's servicer behind our interceptors.

(Temporary until service.server takes interceptors and credentials itself.)
"""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.estimation import EstimationService
from service.servicer import PoseEstimationServicer


@contextmanager
def serve(registry, interceptors=(), credentials=None, workers=4, servicer=None):
    """Yield 'host:port' of a server running in a thread of its own; stop it on exit."""
    started, ready = threading.Event(), {}

    async def main():
        stop = asyncio.Event()
        ready["loop"], ready["stop"] = asyncio.get_running_loop(), stop
        with ThreadPoolExecutor(workers) as executor:
            server = grpc.aio.server(interceptors=list(interceptors))
            pb_grpc.add_PoseEstimationServicer_to_server(
                servicer or PoseEstimationServicer(executor, EstimationService(registry)), server)
            health_servicer = health.aio.HealthServicer()
            health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
            await health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
            address = "127.0.0.1:0"
            ready["port"] = (server.add_secure_port(address, credentials) if credentials
                             else server.add_insecure_port(address))
            await server.start()
            started.set()
            await stop.wait()
            await server.stop(0.5)

    thread = threading.Thread(target=asyncio.run, args=(main(),), daemon=True)
    thread.start()
    started.wait(10)
    try:
        yield f"127.0.0.1:{ready['port']}"
    finally:
        ready["loop"].call_soon_threadsafe(ready["stop"].set)
        thread.join(10)
