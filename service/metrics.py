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

import ssl
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

UNKNOWN_ESTIMATOR = "(unknown)"  # the estimator label of requests for names the registry does not know
LOADING_ESTIMATORS = "(loading)"  # the label of every request that arrives before the estimators are loaded
METRICS_PATH = "/metrics"

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

        server = (_TlsHttpServer if tls is not None else ThreadingHTTPServer)((host, port), Handler)
        server.tls = tls
        server.daemon_threads = True
        thread = threading.Thread(target=server.serve_forever, name="metrics-http", daemon=True)
        thread.start()
        return server, thread


class _TlsHttpServer(ThreadingHTTPServer):
    """HTTPS: each connection's TLS handshake runs in its own thread, so a slow client holds no other scrape."""

    tls: ssl.SSLContext

    def finish_request(self, request, client_address) -> None:
        request.settimeout(10.0)
        try:
            request = self.tls.wrap_socket(request, server_side=True)
        except (OSError, ssl.SSLError):
            return  # a failed handshake: nothing to answer
        super().finish_request(request, client_address)
