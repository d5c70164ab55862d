"""The device's link to the backend: one long-lived `Track` stream on a background thread.

`TrackClient` keeps a bidirectional `Track` stream open, sends the requests the PRM hands it (the
PRM keeps one in flight; a request it abandons may still be answered, and the answer is delivered
like any other) and hands each response to `on_response` on its own thread. When the server goes away, a request outlives its deadline or the
stream breaks, every request in flight is reported to `on_failure` (so the tracker can re-request)
and the client reconnects with exponential backoff and jitter, or later where a server at capacity
says when (gRPC's `grpc-retry-pushback-ms` trailer). Nothing it does raises into the caller.

`make_request` builds an `EstimateRequest` carrying the frame, or the crop of it that
`client_sdk.crop` chose (JPEG bytes from the shell, which sends a stand-in of the paper's 90 kB when
it renders no image), and the tracker's ~10 kB state as `client_state`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Self

import grpc
import numpy as np

from flextrack import wire
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

log = logging.getLogger(__name__)

_END = object()


@dataclass(frozen=True)
class TransportOptions:
    request_timeout_s: float = 1.0  # no response by then: report a failure and reconnect
    connect_timeout_s: float = 0.5  # report "not reachable" after this long without a ready channel (it keeps trying)
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 0.5
    backoff_multiplier: float = 2.0
    jitter: float = 0.2  # each wait is scaled by U(1 - jitter, 1 + jitter)
    seed: int = 0  # for the jitter
    pushback_max_s: float = 10.0  # the longest a server's retry pushback may park the device
    # The server's message limit (`flextrack serve --max-message-mb`, 8 MiB by default): gRPC ends the whole stream
    # on a larger message, so such a frame is refused here and reported to on_failure instead of being sent.
    max_message_bytes: int = 8 * 1024 * 1024
    max_in_flight: int = 64  # requests sent and not yet answered; past it a request is refused like an over-size one


def make_request(*, frame_id: int, capture_time_ns: int, session_id: str = "", estimator: str = "",
                 object_id: str = "", sequence: str = "", image: bytes | None = None,
                 encoding: int = pb.Image.JPEG, width: int = 0, height: int = 0,
                 intrinsics: pb.Intrinsics | None = None, client_state: bytes = b"",
                 prior: pb.PosePrior | None = None, crop: pb.Crop | None = None) -> pb.EstimateRequest:
    """An `EstimateRequest` for one frame (`image=None`: no image at all; `prior`: see `prior_of`). `width` and
    `height` are the image's; with a `crop` (client_sdk.crop) the image holds that rectangle of the frame and
    `intrinsics` stay the full frame's."""
    return pb.EstimateRequest(
        session_id=session_id, frame_id=int(frame_id), capture_time_ns=int(capture_time_ns),
        estimator=estimator, object_id=object_id, sequence=sequence,
        image=None if image is None else pb.Image(encoding=encoding, data=image, width=width, height=height),
        intrinsics=intrinsics, client_state=client_state, prior=prior, crop=crop)


def prior_of(tracker, capture_time_ns: int) -> pb.PosePrior | None:
    """The tracker's predicted T_CO at the capture time and its covariance, for the request's `prior`
    (None before initialisation; no covariance from a tracker that keeps none: the paper's)."""
    T_CO = tracker.pose_at(capture_time_ns)
    if T_CO is None:
        return None
    covariance_at = getattr(tracker, "pose_covariance_at", None)
    cov = covariance_at(capture_time_ns) if covariance_at is not None else None
    return pb.PosePrior(pose=wire.pose_to_pb(T_CO), covariance=wire.covariance_to_pb(cov))


PUSHBACK_KEY = "grpc-retry-pushback-ms"  # gRPC's trailer for "retry no sooner than this" (gRFC A6)


def retry_pushback_s(trailing_metadata) -> float:
    """The wait a refusing server asks for in its `grpc-retry-pushback-ms` trailer, in s (0: none, or unreadable)."""
    for key, value in trailing_metadata or ():
        if key == PUSHBACK_KEY:
            try:
                ms = float(value)
            except ValueError:
                return 0.0
            return ms / 1e3 if ms >= 0 else 0.0  # NaN and negatives ask for nothing
    return 0.0


class Backoff:
    """Exponential backoff with multiplicative jitter; `reset()` after a success."""

    def __init__(self, options: TransportOptions):
        self._o = options
        self._rng = np.random.default_rng(options.seed)
        self._attempt = 0

    def reset(self) -> None:
        self._attempt = 0

    def next_s(self) -> float:
        base = min(self._o.backoff_max_s, self._o.backoff_initial_s * self._o.backoff_multiplier ** self._attempt)
        self._attempt += 1
        return base * self._rng.uniform(1.0 - self._o.jitter, 1.0 + self._o.jitter)


class TrackClient:
    """A `Track` stream that survives the server going away. Use as a context manager."""

    def __init__(self, target: str, on_response: Callable[[pb.EstimateResponse], None],
                 on_failure: Callable[[int, str], None], *,
                 interceptors: Sequence[grpc.StreamStreamClientInterceptor] = (),
                 options: TransportOptions = TransportOptions(),
                 credentials: grpc.ChannelCredentials | None = None, metadata: Sequence[tuple[str, str]] = ()):
        """`credentials`: TLS (and token) channel credentials, client_sdk.credentials; `metadata`: sent with the
        stream, e.g. client_sdk.credentials.token_metadata(token) on a plaintext channel."""
        self._credentials, self._metadata = credentials, tuple(metadata)
        self.target = target
        self._on_response = on_response
        self._on_failure = on_failure
        self._interceptors = list(interceptors)
        self.options = options
        self._backoff = Backoff(options)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._outbox: queue.Queue | None = None  # requests of the current stream; None: not connected
        self._call = None
        self._in_flight: dict[int, float] = {}  # frame id -> monotonic send time
        self._threads: list[threading.Thread] = []
        self.reconnects = 0
        self._pushback_s = 0.0  # what the server asked of the last stream's retry
        self._last_ready_watch = float("-inf")  # monotonic time of the last channel_ready_future

    # -- the caller's side ---------------------------------------------------------------------
    def start(self) -> TrackClient:
        for target in (self._run, self._watchdog):
            t = threading.Thread(target=target, name=f"TrackClient-{target.__name__}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            if self._call is not None:
                self._call.cancel()
        for t in self._threads:
            t.join(timeout=5.0)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._outbox is not None

    @property
    def in_flight(self) -> int:
        with self._lock:
            return len(self._in_flight)

    def wait_connected(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not self.connected and time.monotonic() < deadline and not self._stop.is_set():
            time.sleep(0.01)
        return self.connected

    def submit(self, request: pb.EstimateRequest) -> bool:
        """Send `request` if connected; False (nothing sent) otherwise.

        A request the server could not take (over `max_message_bytes`: gRPC would end the whole stream on it),
        or one past `max_in_flight`, is not sent either: False, and `on_failure(frame_id, reason)` says why.
        """
        size, limit = request.ByteSize(), self.options.max_message_bytes
        if size > limit:
            self._refuse(request.frame_id, f"request of {size} bytes is over the {limit}-byte message limit "
                                           f"(TransportOptions.max_message_bytes, the server's --max-message-mb); not sent")
            return False
        with self._lock:
            if self._outbox is None:
                return False
            full = len(self._in_flight) >= self.options.max_in_flight
            if not full:
                self._in_flight[request.frame_id] = time.monotonic()
                self._outbox.put(request)
                return True
        self._refuse(request.frame_id, f"{self.options.max_in_flight} requests already in flight "
                                       f"(TransportOptions.max_in_flight); not sent")
        return False

    def _refuse(self, frame_id: int, reason: str) -> None:
        log.warning("request refused before sending: %s", reason)
        self._deliver(self._on_failure, frame_id, reason)

    # -- the background side -------------------------------------------------------------------
    def _run(self) -> None:
        # One channel for the client's life: while the server is away, gRPC's own connection backoff
        # (capped at backoff_max_s) keeps trying, so a returning server is seen within that cap.
        # A channel per attempt, closed after connect_timeout_s and followed by a backoff wait, left
        # windows of up to ~1 s with no attempt at all (a recovery test failed at 1.01 s on that).
        o = self.options
        channel_options = [("grpc.initial_reconnect_backoff_ms", max(1, round(o.backoff_initial_s * 1e3))),
                           ("grpc.max_reconnect_backoff_ms", max(1, round(o.backoff_max_s * 1e3)))]
        channel = (grpc.secure_channel(self.target, self._credentials, options=channel_options)
                   if self._credentials is not None else grpc.insecure_channel(self.target, options=channel_options))
        try:
            while not self._stop.is_set():
                reason, streamed = self._one_stream(channel)
                self._fail_in_flight(reason)
                if self._stop.is_set():
                    break
                self.reconnects += 1
                if streamed:  # a stream that broke or was refused: wait before the next one
                    pushback, self._pushback_s = min(self._pushback_s, o.pushback_max_s), 0.0
                    self._stop.wait(max(self._backoff.next_s(), pushback))
        finally:
            # gRPC's connectivity watch, started by channel_ready_future, polls every 0.2 s and fails on a
            # channel closed under it: let a recent one see its last poll first
            time.sleep(max(0.0, self._last_ready_watch + 0.25 - time.monotonic()))
            channel.close()

    def _one_stream(self, channel: grpc.Channel) -> tuple[str, bool]:
        """Wait for the channel, open a stream, pump responses until it breaks; returns why it ended,
        and whether a stream was opened (False: the channel was not ready within connect_timeout_s)."""
        ready = grpc.channel_ready_future(channel)
        self._last_ready_watch = time.monotonic()
        try:
            ready.result(timeout=self.options.connect_timeout_s)
        except grpc.FutureTimeoutError:
            ready.cancel()  # stops its connectivity watch, which would outlive the channel otherwise
            return f"backend {self.target} not reachable", False
        outbox: queue.Queue = queue.Queue()
        stub = pb_grpc.PoseEstimationStub(grpc.intercept_channel(channel, *self._interceptors))
        call = stub.Track(iter(outbox.get, _END), metadata=self._metadata or None)
        with self._lock:
            self._outbox, self._call = outbox, call
        self._backoff.reset()
        try:
            for response in call:
                with self._lock:
                    self._in_flight.pop(response.frame_id, None)
                self._deliver(self._on_response, response)
            return "stream ended by the server", True
        except grpc.RpcError as exc:
            self._pushback_s = retry_pushback_s(exc.trailing_metadata())
            return f"stream broke: {exc.code().name} {exc.details() or ''}".strip(), True
        finally:
            with self._lock:
                self._outbox, self._call = None, None
            outbox.put(_END)
            call.cancel()

    def _watchdog(self) -> None:
        """Cancel the stream when the oldest request outlives its deadline (the reader reconnects)."""
        while not self._stop.wait(0.02):
            with self._lock:
                oldest = min(self._in_flight.values(), default=None)
                if (oldest is not None and self._call is not None
                        and time.monotonic() - oldest > self.options.request_timeout_s):
                    self._call.cancel()

    def _fail_in_flight(self, reason: str) -> None:
        with self._lock:
            failed, self._in_flight = list(self._in_flight), {}
        for frame_id in failed:
            self._deliver(self._on_failure, frame_id, reason)

    @staticmethod
    def _deliver(callback, *args) -> None:
        try:
            callback(*args)
        except Exception:  # a faulty callback must not kill the stream
            log.exception("TrackClient callback failed")
