"""Prometheus metrics of the backend: what an operator needs to see load, errors and saturation.

- `flextrack_requests_total{method, estimator, code}`: every frame answered, by outcome (`OK`, a
  response status such as `OBJECT_NOT_FOUND`, or a gRPC code such as `RESOURCE_EXHAUSTED` when the
  admission queue was full).
- `flextrack_request_latency_seconds{method, estimator}`: time from the frame reaching the servicer
  to its answer, as a histogram.
- `flextrack_queue_depth{estimator}`: frames admitted and not yet answered.
- `flextrack_streams`: open Track streams (devices connected).
- `flextrack_batch_size{estimator}`: frames per call of a batching estimator.

Each `ServiceMetrics` has its own CollectorRegistry, so several servers (tests, replicas in one
process) do not collide; `serve_http` exposes it on /metrics (only there: any other path is 404)
on the address the operator gives, loopback by default.

Labels are bounded: the `estimator` label is a registered name, "-" for a refused stream or
`UNKNOWN_ESTIMATOR` for any name the registry does not know (the admission interceptor resolves
names so), never the client's raw string, so that unknown names cannot grow the page.
"""

from __future__ import annotations

import logging
import queue
import selectors
import socket
import ssl
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from http.server import BaseHTTPRequestHandler, HTTPServer

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

UNKNOWN_ESTIMATOR = "(unknown)"  # the estimator label of requests for names the registry does not know
LOADING_ESTIMATORS = "(loading)"  # the label of every request that arrives before the estimators are loaded
METRICS_PATH = "/metrics"
METRICS_THREADS = 4  # scrapes answered at once
METRICS_IDLE_S = 10.0  # a connection whose request has not arrived (or stalls) within this is closed
MAX_METRICS_CONNECTIONS = 256  # connections held at once; past it a new one is closed at once

log = logging.getLogger("flextrack.service")

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.033, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)
BATCH_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 64)


class ServiceMetrics:
    def __init__(self, registry: CollectorRegistry | None = None):
        self.registry = registry or CollectorRegistry()
        self._children: dict[tuple, object] = {}
        self.requests = Counter("flextrack_requests", "Frames answered, by method, estimator and outcome code",
                                ["method", "estimator", "code"], registry=self.registry)
        self.latency = Histogram("flextrack_request_latency_seconds", "Time from a frame reaching the servicer to "
                                 "its answer", ["method", "estimator"], buckets=LATENCY_BUCKETS_S,
                                 registry=self.registry)
        self.queue_depth = Gauge("flextrack_queue_depth", "Frames admitted and not yet answered, per estimator",
                                 ["estimator"], registry=self.registry)
        self.streams = Gauge("flextrack_streams", "Open Track streams", registry=self.registry)
        self.batch_size = Histogram("flextrack_batch_size", "Frames per batched estimator call", ["estimator"],
                                    buckets=BATCH_BUCKETS, registry=self.registry)

    def observe(self, method: str, estimator: str, code: str, seconds: float | None) -> None:
        """One answered frame; `seconds` None for frames refused before any work (not in the histogram)."""
        key = (method, estimator, code)
        counter = self._children.get(key)  # labels() costs a lock and a lookup: keep the children at hand
        if counter is None:
            counter = self._children[key] = self.requests.labels(*key)
        counter.inc()
        if seconds is not None:
            histogram = self._children.get(key[:2])
            if histogram is None:
                histogram = self._children[key[:2]] = self.latency.labels(method, estimator)
            histogram.observe(seconds)

    def set_queue_depth(self, estimator: str, depth: int) -> None:
        self.queue_depth.labels(estimator).set(depth)

    def set_streams(self, count: int) -> None:
        self.streams.set(count)

    def observe_batch(self, estimator: str, size: int) -> None:
        self.batch_size.labels(estimator).observe(size)

    def count(self, code: str, method: str | None = None, estimator: str | None = None) -> float:
        """Sum of `flextrack_requests_total` over the labels not given (for tests and benchmarks)."""
        total = 0.0
        for metric in self.registry.collect():
            for sample in metric.samples:
                if sample.name != "flextrack_requests_total" or sample.labels["code"] != code:
                    continue
                if method not in (None, sample.labels["method"]) or estimator not in (None, sample.labels["estimator"]):
                    continue
                total += sample.value
        return total

    def serve_http(self, port: int, host: str = "127.0.0.1", authorize: Callable[[str | None], bool] | None = None,
                   tls: ssl.SSLContext | None = None):
        """Expose /metrics (and nothing else) on host:port in a daemon thread; returns (http server, thread).

        `authorize(authorization header or None)`: when given, a scrape it refuses gets 401; `tls`: HTTPS."""
        registry = self.registry

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # http.server calls it by this name
                if self.path.split("?", 1)[0] != METRICS_PATH:
                    self.send_error(404, "only /metrics is served here")
                    return
                if authorize is not None and not authorize(self.headers.get("Authorization")):
                    self.send_response(401)
                    self.send_header("WWW-Authenticate", 'Bearer realm="metrics"')
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                body = generate_latest(registry)
                self.send_response(200)
                self.send_header("Content-Type", CONTENT_TYPE_LATEST)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args) -> None:  # no access lines on stderr: the log is JSON lines
                pass

        server = _MetricsHttpServer((host, port), Handler, tls)
        thread = threading.Thread(target=server.serve_forever, name="metrics-http", daemon=True)
        thread.start()
        return server, thread


class _MetricsHttpServer(HTTPServer):
    """HTTP(S) with a bounded cost per connection: accepted connections wait for their request in one selector
    thread (no thread each), a readable one is answered by a pool of METRICS_THREADS (its TLS handshake there too),
    every read and write times out after METRICS_IDLE_S."""

    request_queue_size = 128  # the listen backlog (socketserver's 5 makes a burst of connections wait seconds)

    def __init__(self, address, handler, tls: ssl.SSLContext | None = None):
        self.tls = tls
        self._pool = ThreadPoolExecutor(METRICS_THREADS, thread_name_prefix="metrics")
        self._selector = selectors.DefaultSelector()
        self._arrivals: queue.SimpleQueue = queue.SimpleQueue()
        self._wake_read, self._wake_write = socket.socketpair()
        self._selector.register(self._wake_read, selectors.EVENT_READ)
        self._held = 0  # connections accepted and not yet closed
        self._deadlines: dict[socket.socket, float] = {}  # connections waiting for their request (selector thread)
        self._lock = threading.Lock()
        self._closing = False
        self._waiter = threading.Thread(target=self._wait_for_requests, name="metrics-idle", daemon=True)
        self._waiter.start()
        super().__init__(address, handler)  # last: a failed bind calls server_close, which stops the waiter

    def process_request(self, request, client_address) -> None:
        """In serve_forever's thread, for each accepted connection: hand it to the selector thread."""
        with self._lock:
            if self._held >= MAX_METRICS_CONNECTIONS:
                super().shutdown_request(request)
                return
            self._held += 1
        self._arrivals.put(request)
        self._wake_write.send(b"\0")

    def _wait_for_requests(self) -> None:
        deadlines = self._deadlines
        while not self._closing:
            timeout = max(0.0, min(deadlines.values()) - time.monotonic()) if deadlines else None
            for key, _ in self._selector.select(timeout):
                if key.fileobj is self._wake_read:
                    self._wake_read.recv(4096)
                    while not self._arrivals.empty():
                        request = self._arrivals.get()
                        deadlines[request] = time.monotonic() + METRICS_IDLE_S
                        self._selector.register(request, selectors.EVENT_READ)
                    continue
                self._selector.unregister(key.fileobj)
                del deadlines[key.fileobj]
                self._pool.submit(self._answer, key.fileobj)
            now = time.monotonic()
            for request in [r for r, deadline in deadlines.items() if deadline <= now]:  # idle too long
                self._selector.unregister(request)
                del deadlines[request]
                self.shutdown_request(request)

    def _answer(self, request: socket.socket) -> None:
        try:
            request.settimeout(METRICS_IDLE_S)
            if self.tls is not None:
                request = self.tls.wrap_socket(request, server_side=True)
            self.finish_request(request, request.getpeername())
        except (OSError, ssl.SSLError):
            pass  # the client went away, stalled or failed its handshake: nothing to answer, nothing to say
        except Exception as exc:  # noqa: BLE001 - one JSON line, never a traceback on stderr
            log.warning("metrics request failed", extra={"error": repr(exc)})
        finally:
            self.shutdown_request(request)

    def shutdown_request(self, request) -> None:
        super().shutdown_request(request)
        with self._lock:
            self._held -= 1

    def server_close(self) -> None:
        super().server_close()
        self._closing = True
        self._wake_write.send(b"\0")
        self._waiter.join()
        for request in list(self._deadlines):
            self.shutdown_request(request)
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._selector.close()
        self._wake_read.close()
        self._wake_write.close()
