"""What a production server adds around the servicer, gathered from `flextrack serve` flags:
TLS (and mutual TLS), bearer tokens, the admission bound, dynamic batching and the metrics endpoint.

The server (service.server) asks this object for its interceptors, its port credentials, the
registry to serve (batching wraps estimators that can batch) and starts the metrics endpoint; with
the defaults it adds only the admission interceptor without a bound (which parses requests safely
and feeds the metrics), so a plain `flextrack serve` behaves as before.
"""

from __future__ import annotations

import argparse
import logging
import ssl
from dataclasses import dataclass, field
from pathlib import Path

import grpc

from estimators.registry import EstimatorRegistry
from service import security
from service.admission import AdmissionInterceptor
from service.batching import with_batching
from service.limits import RequestLimits
from service.metrics import UNKNOWN_ESTIMATOR, ServiceMetrics

log = logging.getLogger("flextrack.service")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("security, capacity and metrics (docs/operations.md)")
    group.add_argument("--tls-cert", type=Path, help="serve TLS with this certificate chain (PEM)")
    group.add_argument("--tls-key", type=Path, help="private key of --tls-cert (PEM)")
    group.add_argument("--client-ca", type=Path, help="mutual TLS: require client certificates signed by this CA")
    group.add_argument("--token-file", type=Path,
                       help="require 'authorization: Bearer <token>' with one of the tokens in this file (one a line); "
                            "health checks stay open")
    group.add_argument("--max-queue", type=int, default=0,
                       help="frames per estimator let in at once; past it Estimate gets RESOURCE_EXHAUSTED and a "
                            "Track frame status UNAVAILABLE at once (0 = no bound)")
    group.add_argument("--max-streams", type=int, default=0,
                       help="open Track streams (devices) served at once; past it a new stream fails at once with "
                            "RESOURCE_EXHAUSTED (0 = no bound; set it from `flextrack bench capacity`)")
    group.add_argument("--retry-pushback-ms", type=float, default=2000.0,
                       help="a refused stream tells its device to wait about this long (jittered +-50 %%) before it "
                            "retries, in gRPC's grpc-retry-pushback-ms trailer (0 = say nothing)")
    group.add_argument("--max-batch", type=int, default=1,
                       help="dynamic batching: most frames per call of an estimator that can batch (1 = off)")
    group.add_argument("--batch-delay-ms", type=float, default=2.0,
                       help="dynamic batching: longest a frame waits for others to join its batch")
    group.add_argument("--metrics-port", type=int, default=0, help="serve Prometheus /metrics on this port (0 = off)")
    group.add_argument("--metrics-host", default="127.0.0.1",
                       help="address /metrics listens on: loopback by default; 0.0.0.0 for a scraper on another host "
                            "(plain HTTP, no token, unless --metrics-auth: keep it on a private network)")
    group.add_argument("--metrics-auth", action="store_true",
                       help="/metrics takes the bearer tokens of --token-file and, with --tls-cert, HTTPS with the "
                            "same certificate (Prometheus: authorization credentials_file, scheme https)")
    limits = parser.add_argument_group("request limits (checked before any work; docs/operations.md)")
    limits.add_argument("--max-image-pixels", type=int, default=RequestLimits.max_image_pixels,
                        help="largest image (width x height, from the JPEG/PNG header, before decoding) a request may "
                             "carry; larger ones get INVALID_ARGUMENT")
    limits.add_argument("--max-name-chars", type=int, default=RequestLimits.max_name_chars,
                        help="longest estimator, object_id, sequence and session_id a request may carry")
    limits.add_argument("--max-keypoints", type=int, default=RequestLimits.max_keypoints,
                        help="most keypoints a request may carry")


@dataclass
class Hardening:
    tls_cert: Path | None = None
    tls_key: Path | None = None
    client_ca: Path | None = None
    tokens: list[str] = field(default_factory=list)
    max_queue: int = 0
    max_streams: int = 0
    retry_pushback_ms: float = 2000.0
    max_batch: int = 1
    batch_delay_ms: float = 2.0
    metrics_port: int = 0
    metrics_host: str = "127.0.0.1"
    limits: RequestLimits = field(default_factory=RequestLimits)
    metrics_auth: bool = False  # /metrics behind the tokens and TLS of the gRPC port
    metrics: ServiceMetrics = field(default_factory=ServiceMetrics)
    admission: AdmissionInterceptor | None = None

    def __post_init__(self) -> None:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("TLS needs both --tls-cert and --tls-key")
        if self.client_ca is not None and self.tls_cert is None:
            raise ValueError("--client-ca (mutual TLS) needs --tls-cert and --tls-key")
        if self.metrics_auth and not (self.tokens or self.tls_cert):
            raise ValueError("--metrics-auth needs --token-file or --tls-cert/--tls-key to protect /metrics with")
        if self.max_batch < 1 or self.batch_delay_ms < 0 or self.metrics_port < 0:
            raise ValueError("--max-batch >= 1, --batch-delay-ms >= 0 and --metrics-port >= 0 are required")
        self.admission = AdmissionInterceptor(self.max_queue, self.metrics, max_streams=self.max_streams,
                                              retry_pushback_ms=self.retry_pushback_ms)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Hardening:
        """Read the flags of add_arguments; files are read now, so a bad path fails before serving."""
        tokens = security.load_tokens(args.token_file) if args.token_file else []
        limits = RequestLimits(args.max_name_chars, args.max_keypoints, args.max_image_pixels)
        hardening = cls(args.tls_cert, args.tls_key, args.client_ca, tokens, args.max_queue, args.max_streams,
                        args.retry_pushback_ms, args.max_batch, args.batch_delay_ms, args.metrics_port,
                        args.metrics_host, limits, args.metrics_auth)
        hardening.credentials()  # reads and checks the PEM files
        return hardening

    def interceptors(self) -> list[grpc.aio.ServerInterceptor]:
        """Authentication first (a refused call costs nothing more), then admission and metrics."""
        return ([security.BearerTokenInterceptor(self.tokens)] if self.tokens else []) + [self.admission]

    @property
    def authenticates(self) -> bool:
        """Whether a caller must prove something (TLS or a token) before it is served."""
        return self.tls_cert is not None or bool(self.tokens)

    def credentials(self) -> grpc.ServerCredentials | None:
        if self.tls_cert is None:
            return None
        return security.server_credentials(self.tls_cert, self.tls_key, self.client_ca)

    def workers(self, requested: int) -> int:
        """Estimator threads: a batch can only fill if at least max_batch frames can wait for it at once."""
        return max(requested, 2 * self.max_batch) if self.max_batch > 1 else requested

    def prepare(self, registry: EstimatorRegistry) -> EstimatorRegistry:
        """The registry to serve: batch-capable estimators wrapped; admission counts '' as the default."""
        registry, batched = with_batching(registry, self.max_batch, self.batch_delay_ms / 1e3, self.metrics)
        if batched:
            log.info("dynamic batching", extra={"estimators": batched, "max_batch": self.max_batch,
                                                "batch_delay_ms": self.batch_delay_ms})
        # Metrics labels and queue depths are keyed by this name: a registered one, or one shared label for every
        # name the registry does not know (a client's raw strings would grow the metrics page without bound).
        default, known = registry.default or "", frozenset(registry.names())
        self.admission.resolve = lambda name: (name or default) if (name or default) in known else UNKNOWN_ESTIMATOR
        return registry

    def start_metrics(self):
        """Start /metrics when a port is set; returns the HTTP server (or None)."""
        if not self.metrics_port:
            return None
        authorize, tls = None, None
        if self.metrics_auth:
            if self.tokens:
                authorize = security.BearerTokenInterceptor(self.tokens).is_valid
            if self.tls_cert is not None:
                tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
                tls.load_cert_chain(self.tls_cert, self.tls_key)
        try:
            http_server, _ = self.metrics.serve_http(self.metrics_port, self.metrics_host, authorize, tls)
        except OSError as exc:
            raise OSError(f"cannot serve /metrics on {self.metrics_host}:{self.metrics_port}: "
                          f"{exc.strerror or exc}") from None
        log.info("metrics", extra={"address": f"{self.metrics_host}:{self.metrics_port}", "path": "/metrics",
                                   "token": bool(authorize), "tls": tls is not None})
        return http_server
