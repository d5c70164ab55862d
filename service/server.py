"""The grpc.aio server: PoseEstimation + health + reflection, run in the foreground or a thread.

`serve` is what `flextrack serve` runs: it starts listening at once with health NOT_SERVING,
loads the estimators, turns SERVING, and on SIGTERM turns NOT_SERVING while it keeps serving for
the drain period (so that an orchestrator's readiness probe fails and traffic moves away before
the socket closes), then stops taking calls, lets in-flight ones finish within the grace period
and returns 0: a call still running then (a decode or a network, which a thread cannot be made to
stop) is left behind with the process, which exits within drain + grace. SIGINT, or a second signal, skips the drain. It refuses a port another server
holds (gRPC would share it through SO_REUSEPORT). `BackgroundServer` runs the same server on a
free loopback port in a thread of its own, for runners, the demo and tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import gc
import json
import logging
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Self

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from estimators.registry import EstimatorRegistry
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.estimation import EstimationService
from service.hardening import Hardening
from service.servicer import PoseEstimationServicer

log = logging.getLogger("flextrack.service")

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["PoseEstimation"].full_name
DEFAULT_MAX_MESSAGE_MB = 8
DEFAULT_GRACE_S = 5.0
DEFAULT_DRAIN_S = 5.0
DEFAULT_HOST = "127.0.0.1"
DEFAULT_WORKERS = 4
ABANDON_S = 0.5  # after the grace, the time calls get to send their UNAVAILABLE before gRPC cancels them


class JsonLogFormatter(logging.Formatter):
    """One JSON object a line: time, level, logger, message and any `extra=` fields."""

    _STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime", "taskName"}

    def format(self, record: logging.LogRecord) -> str:
        doc = {"ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
               "level": record.levelname, "logger": record.name, "msg": record.getMessage()}
        doc.update({k: v for k, v in vars(record).items() if k not in self._STANDARD})
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


class CurrentStderrHandler(logging.StreamHandler):
    """A stream handler on sys.stderr as it is when a record is emitted, not when the handler was made: whoever
    replaces sys.stderr later (route_native_stderr; a test's capture, closed after it) is written to, never a
    stream that has since been closed."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler sets it; the current sys.stderr is always used
        pass


def configure_logging(level: str = "INFO") -> None:
    """JSON lines on stderr for everything the process says: Python's warnings go through logging, and OpenCV's
    own log lines are off (images are decoded with Pillow, which prints nothing, service.request_decoding);
    what other native libraries print, `serve` routes (route_native_stderr)."""
    handler = CurrentStderrHandler()
    handler.setFormatter(JsonLogFormatter())
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)
    logging.captureWarnings(True)
    quiet_native_logs()


def quiet_native_logs() -> None:
    """Keep OpenCV's native log lines ("[ WARN:0@...]") off stderr, where they would break the JSON lines."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


class EstimatorThreads(Executor):
    """A fixed pool of daemon threads for the estimators. Why not ThreadPoolExecutor: the interpreter joins its
    threads at exit, so a server told to stop waited for a long decode or network call (19.6 s where drain +
    grace was 3 s); daemon threads are left behind with the process, as the calls they ran already were."""

    def __init__(self, workers: int, name: str = "estimator"):
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.busy = 0  # threads inside a call now
        self._threads = [threading.Thread(target=self._work, name=f"{name}_{i}", daemon=True) for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        self._queue.put((future, fn, args, kwargs))
        return future

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            future, fn, args, kwargs = item
            if not future.set_running_or_notify_cancel():
                continue
            with self._lock:
                self.busy += 1
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001 - the caller's to see, through the future
                future.set_exception(exc)
            finally:
                with self._lock:
                    self.busy -= 1

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop the threads once their queue is done (`cancel_futures`: drop what is queued); `wait`: join them."""
        if cancel_futures:
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[0].cancel()
        for _ in self._threads:
            self._queue.put(None)
        if wait:
            for thread in self._threads:
                thread.join()


NATIVE_LEVELS = {"I": logging.INFO, "W": logging.WARNING, "E": logging.ERROR, "F": logging.CRITICAL}


def route_native_stderr() -> None:
    """Make what native libraries write to file descriptor 2 themselves JSON records too (logger "native").

    gRPC core prints a line per failed TLS handshake, which any client can cause ("I1128 09:28:01.558471 22742
    ssl_transport_security.cc:2563] Handshake failed ..."; its level is the first letter), and it reads
    GRPC_VERBOSITY only when it is imported, before any code of ours runs; onnxruntime and others print too.
    Descriptor 2 becomes a pipe whose lines a thread logs; Python's own sys.stderr, and so the JSON handler,
    keeps the real one. Only `serve` calls this: it changes the whole process."""
    try:
        real = os.dup(2)
    except OSError:  # no stderr at all: nothing to keep JSON
        return
    read, write = os.pipe()
    with contextlib.suppress(AttributeError, OSError):  # Linux: room for bursts (64 kB by default)
        fcntl.fcntl(write, fcntl.F_SETPIPE_SZ, 1 << 20)
    os.set_blocking(write, False)  # a burst the thread cannot keep up with loses lines, never stalls gRPC's threads
    os.dup2(write, 2)
    os.close(write)
    previous = sys.stderr
    sys.stderr = open(real, "w", buffering=1, encoding="utf-8", errors="backslashreplace")  # noqa: SIM115 - for good
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.StreamHandler) and handler.stream is previous:
            handler.setStream(sys.stderr)
    native = logging.getLogger("native")

    def forward() -> None:
        with open(read, "rb") as lines:
            for raw in lines:
                line = raw.decode("utf-8", "backslashreplace").rstrip()
                if line:
                    native.log(NATIVE_LEVELS.get(line[0], logging.WARNING) if line[1:2].isdigit() else logging.WARNING,
                               line)

    threading.Thread(target=forward, name="native-stderr", daemon=True).start()


class PortInUse(OSError):
    """The address is held by another process (or another flextrack server)."""


@dataclass
class RunningServer:
    server: grpc.aio.Server
    port: int
    servicer: PoseEstimationServicer
    health: health.aio.HealthServicer
    hardening: Hardening | None = None  # TLS, tokens, admission, batching, metrics
    metrics_http: object = None  # the /metrics HTTP server, when one runs

    async def set_registry(self, registry: EstimatorRegistry) -> None:
        """Start answering with these estimators; health turns SERVING once they are all ready."""
        limits = None
        if self.hardening is not None:
            registry = self.hardening.prepare(registry)  # batching wraps the estimators that can batch
            limits = self.hardening.limits
        self.servicer.service = EstimationService(registry, limits)
        status = health_pb2.HealthCheckResponse.SERVING if registry.ready else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", SERVICE_NAME):
            await self.health.set(name, status)

    async def drain(self) -> None:
        """Health NOT_SERVING for good (probes fail, load balancers move away); calls are still served."""
        await self.health.enter_graceful_shutdown()

    async def stop(self, grace_s: float) -> None:
        """Take no new calls; those in flight get `grace_s` to end, then end UNAVAILABLE (their threads, which
        cannot be stopped, left behind): the server stops within grace_s + ABANDON_S whatever runs."""
        await self.health.enter_graceful_shutdown()
        stopping = asyncio.ensure_future(self.server.stop(grace_s + ABANDON_S))
        await asyncio.wait([stopping], timeout=grace_s)
        self.servicer.abandon()
        if self.hardening is not None and self.hardening.admission is not None:
            self.hardening.admission.stopping = True
        await stopping
        if self.metrics_http is not None:
            self.metrics_http.shutdown()
            self.metrics_http.server_close()


async def start_server(host: str, port: int, executor: Executor,
                       max_message_mb: float = DEFAULT_MAX_MESSAGE_MB,
                       hardening: Hardening | None = None) -> RunningServer:
    """Listen on host:port (0 = any free port) with health NOT_SERVING and no estimators yet."""
    max_bytes = int(max_message_mb * 1024 * 1024)
    # grpc.so_reuseport 0: gRPC sets SO_REUSEPORT by default, so a second server on a held port would start
    # silently and the two would share the connections; without it the bind fails and we say so.
    server = grpc.aio.server(interceptors=hardening.interceptors() if hardening else None,
                             options=[("grpc.max_receive_message_length", max_bytes),
                                      ("grpc.max_send_message_length", max_bytes),
                                      ("grpc.so_reuseport", 0)])
    servicer = PoseEstimationServicer(executor)
    pb_grpc.add_PoseEstimationServicer_to_server(servicer, server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection((SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), server)
    for name in ("", SERVICE_NAME):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.NOT_SERVING)
    credentials = hardening.credentials() if hardening else None
    address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    _probe_bind(host, port, address)  # before gRPC, whose failed bind also prints a native error line
    try:
        bound = (server.add_secure_port(address, credentials) if credentials
                 else server.add_insecure_port(address))
    except RuntimeError:  # grpc.aio raises on a failed bind, older versions return 0
        bound = 0
    if bound == 0:
        raise PortInUse(f"cannot listen on {address}: the port is in use (another server holds it) or the address "
                        f"is not one of this host's")
    metrics_http = hardening.start_metrics() if hardening else None  # before start: a taken port stops nothing
    try:
        await server.start()
    except BaseException:
        if metrics_http is not None:
            metrics_http.shutdown()
            metrics_http.server_close()
        raise
    return RunningServer(server, bound, servicer, health_servicer, hardening, metrics_http)


def _probe_bind(host: str, port: int, address: str) -> None:
    """Raise PortInUse when host:port cannot be bound (held by another server or program)."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host.strip("[]") or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError:
        return  # gRPC says why
    for family, kind, proto, _, sockaddr in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as gRPC: a TIME_WAIT port is free
            try:
                probe.bind(sockaddr)
            except OSError as exc:
                raise PortInUse(f"cannot listen on {address}: {exc.strerror or exc} (the port is in use: another "
                                f"server holds it, or the address is not one of this host's)") from None


async def serve(load_registry: Callable[[], EstimatorRegistry], host: str = DEFAULT_HOST, port: int = 50051,
                max_message_mb: float = DEFAULT_MAX_MESSAGE_MB, grace_s: float = DEFAULT_GRACE_S,
                workers: int = DEFAULT_WORKERS, on_serving: Callable[[int], None] | None = None,
                hardening: Hardening | None = None, drain_s: float = DEFAULT_DRAIN_S) -> int:
    """Run until SIGTERM/SIGINT; 0 after a graceful stop, 1 when the estimators fail to load.

    SIGTERM drains first: health NOT_SERVING for `drain_s` while calls are still served; SIGINT or a
    second signal stops at once (in-flight calls still get `grace_s`). `on_serving(port)` is called
    once the server is SERVING (the benchmark learns its port so). Raises PortInUse when it cannot listen.
    """
    loop = asyncio.get_running_loop()
    stop, signals = asyncio.Event(), []

    def on_signal(sig: signal.Signals) -> None:
        signals.append(sig)
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal, sig)
    route_native_stderr()
    executor = EstimatorThreads(hardening.workers(workers) if hardening else workers)
    try:
        running = await start_server(host, port, executor, max_message_mb, hardening)
        log.info("listening", extra={"address": f"{host}:{running.port}", "max_message_mb": max_message_mb})
        try:
            registry = await loop.run_in_executor(executor, load_registry)
        except Exception as exc:  # noqa: BLE001 - any load failure: one clean log line and exit 1, no trace
            log.error("estimators failed to load", extra={"error": str(exc)})
            await running.stop(0)
            return 1
        await running.set_registry(registry)
        gc.freeze()  # the loaded models and modules never die: keep them out of every later GC pass
        log.info("serving", extra={"estimators": registry.names(), "default": registry.default})
        if on_serving is not None:
            on_serving(running.port)
        await stop.wait()
        if signals[0] == signal.SIGTERM and drain_s > 0:
            await running.drain()
            log.info("draining", extra={"drain_s": drain_s, "health": "NOT_SERVING"})
            stop.clear()
            try:  # a second signal ends the drain early
                await asyncio.wait_for(stop.wait(), drain_s)
            except TimeoutError:
                pass
        log.info("shutting down", extra={"grace_s": grace_s})
        await running.stop(grace_s)
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
    log.info("stopped", extra={"abandoned": executor.busy})  # calls whose threads still ran: left with the process
    return 0


class BackgroundServer:
    """The server in a background thread on 127.0.0.1, port chosen by the OS.

        with BackgroundServer(registry) as srv:
            channel = grpc.insecure_channel(srv.address)
    """

    def __init__(self, registry: EstimatorRegistry, host: str = "127.0.0.1", port: int = 0,
                 max_message_mb: float = DEFAULT_MAX_MESSAGE_MB, grace_s: float = 1.0, workers: int = DEFAULT_WORKERS,
                 hardening: Hardening | None = None):
        self.registry = registry
        self.hardening = hardening  # TLS, tokens, admission, batching, metrics (service.hardening)
        self._host, self._port, self._max_message_mb = host, port, max_message_mb
        self._grace_s, self._workers = grace_s, workers
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self.port = 0
        self.running: RunningServer | None = None  # the server's parts (servicer, health), once started

    @property
    def address(self) -> str:
        return f"{self._host}:{self.port}"

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        workers = self.hardening.workers(self._workers) if self.hardening else self._workers
        executor = EstimatorThreads(workers)
        try:
            try:
                running = await start_server(self._host, self._port, executor, self._max_message_mb, self.hardening)
                await running.set_registry(self.registry)
            except Exception as exc:  # noqa: BLE001 - re-raised in the thread that called start()
                self._error = exc
                self._started.set()
                return
            self.port, self.running = running.port, running
            self._started.set()
            await self._stop.wait()
            await running.stop(self._grace_s)
        finally:
            executor.shutdown()  # in a process that goes on (tests, runners): its calls end before stop() returns

    def start(self) -> Self:
        self._thread = threading.Thread(target=asyncio.run, args=(self._main(),), name="flextrack-server", daemon=True)
        self._thread.start()
        self._started.wait()
        if self._error is not None:
            raise RuntimeError(f"server failed to start: {self._error}") from self._error
        return self

    def stop(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
            self._thread.join()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
