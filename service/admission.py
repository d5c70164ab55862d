"""Admission control: a bounded work queue per estimator and a bound on Track streams, as a server interceptor.

Why: past its capacity a server that queues everything answers everyone late (latency grows
without limit and every device loses tracking). With a bound, the frames over it are refused at
once and cheaply, and the frames let in keep a short wait. A device treats a refusal like a lost
frame: it keeps tracking on its IMU and sends the next frame.

The bound counts frames of one estimator that were let in and not yet answered (waiting for a
worker thread or running; a cancelled call keeps its place until its worker thread is done with
it, since a thread cannot be stopped, and is counted as CANCELLED). Past it:
- `Estimate` fails at once with RESOURCE_EXHAUSTED;
- `Track` answers that frame at once with status UNAVAILABLE (the stream goes on; a bad frame never
  ends it).
A queue bound protects an estimator that is the bottleneck (a network). When the bottleneck is the
server's own transport (a cheap estimator, 100 kB frames), refusing single frames saves little: each
refused frame was still received and parsed. There the bound that works is on devices: past
`max_streams` open Track streams a new stream fails at once with RESOURCE_EXHAUSTED, before any frame
is read; the device keeps tracking on its IMU and retries with backoff (or, behind round_robin, is
served by another replica). The refusal carries gRPC's `grpc-retry-pushback-ms` trailer (about
`retry_pushback_ms`, jittered so that devices refused together do not come back together): a
device that waits that long spares the server a retry storm, in which every refusal is work on the
same event loop that serves the admitted streams. Health checks are never bounded. An admitted
stream gets its initial metadata at once: a client can wait for admission (metadata or refusal)
before its first frame.

The interceptor also feeds the metrics (service.metrics): every answer's outcome and latency, and
the queue depth, and parses the request bytes itself, so that bytes that are not a request message
get INVALID_ARGUMENT (unary) or an INVALID_INPUT answer (stream) rather than gRPC's own UNKNOWN
with a Python exception name. It wraps the servicer's handlers: the servicer knows nothing of it.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections import defaultdict
from collections.abc import Callable

import grpc
from google.protobuf.message import DecodeError

from flextrack.v1 import pose_estimation_pb2 as pb
from service.metrics import LOADING_ESTIMATORS, ServiceMetrics

SERVICE_PREFIX = "/flextrack.v1.PoseEstimation/"
REJECTED_CODE = "RESOURCE_EXHAUSTED"
PUSHBACK_KEY = "grpc-retry-pushback-ms"  # gRPC's own trailer for "retry no sooner than this" (gRFC A6)


def overload_message(estimator: str, limit: int) -> str:
    return f"estimator '{estimator}' is at capacity ({limit} frames in progress); frame refused, send the next one"


class AdmissionInterceptor(grpc.aio.ServerInterceptor):
    """Bounds in-progress frames per estimator (0 = no bound) and records metrics for every frame.

    `resolve` maps a request's estimator field to the name it is counted under (the server passes
    one that turns "" into the registry's default).
    """

    def __init__(self, max_queue: int = 0, metrics: ServiceMetrics | None = None,
                 resolve: Callable[[str], str] | None = None, max_streams: int = 0, retry_pushback_ms: float = 0.0):
        if max_queue < 0 or max_streams < 0 or not retry_pushback_ms >= 0:
            raise ValueError(f"max_queue, max_streams and retry_pushback_ms must be >= 0 (0 = unbounded / none), "
                             f"got {max_queue}, {max_streams}, {retry_pushback_ms}")
        self.max_queue, self.max_streams = max_queue, max_streams
        self.retry_pushback_ms = retry_pushback_ms
        self._jitter = random.Random(0)
        self.streams = 0  # open Track streams
        self.metrics = metrics
        # until the server resolves names against its registry (estimators still loading), every request
        # counts under one label: a client's raw strings must not grow the counters or the metrics page
        self.resolve = resolve or (lambda name: LOADING_ESTIMATORS)
        self._depth: dict[str, int] = defaultdict(int)  # the event loop is one thread: no lock needed
        self.stopping = False  # set when the server stops: a stream cancelled then ends quietly

    def depth(self, estimator: str) -> int:
        return self._depth[estimator]

    def _admit(self, estimator: str) -> bool:
        if self.max_queue and self._depth[estimator] >= self.max_queue:
            return False
        self._set_depth(estimator, +1)
        return True

    def _set_depth(self, estimator: str, delta: int) -> None:
        self._depth[estimator] += delta
        if self.metrics:
            self.metrics.set_queue_depth(estimator, self._depth[estimator])

    def _observe(self, method: str, estimator: str, code: str, started: float | None) -> None:
        if self.metrics:
            self.metrics.observe(method, estimator, code, None if started is None else time.perf_counter() - started)

    async def intercept_service(self, continuation, handler_call_details):
        handler = await continuation(handler_call_details)
        method = handler_call_details.method or ""
        if handler is None or not method.startswith(SERVICE_PREFIX):
            return handler
        name, parse = method[len(SERVICE_PREFIX):], handler.request_deserializer
        # The wrappers get the raw bytes (deserializer None) and parse them themselves, so that bytes
        # that are not the request message get a clear answer instead of gRPC's UNKNOWN + exception name.
        if not handler.request_streaming and not handler.response_streaming:
            wrap = self._wrap_estimate if name == "Estimate" else _wrap_parse_only
            return grpc.unary_unary_rpc_method_handler(wrap(handler.unary_unary, parse),
                                                       response_serializer=handler.response_serializer)
        if name == "Track" and handler.request_streaming and handler.response_streaming:
            return grpc.stream_stream_rpc_method_handler(self._wrap_track(handler.stream_stream, parse),
                                                         response_serializer=handler.response_serializer)
        return handler

    def _wrap_estimate(self, behaviour, parse):
        async def estimate(raw, context):
            request = await _parse_or_abort(parse, raw, context)
            estimator = self.resolve(request.estimator)
            if not self._admit(estimator):
                self._observe("Estimate", estimator, REJECTED_CODE, None)
                await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, overload_message(estimator, self.max_queue))
            started, code = time.perf_counter(), "INTERNAL"
            try:
                response = await behaviour(request, context)
                code = pb.EstimateResponse.Status.Name(response.status)
                return response
            except asyncio.CancelledError:  # the client cancelled, or the deadline passed; the work has ended
                code = _cancelled_code(context)
                raise
            except Exception:
                status = context.code()  # set by the servicer's abort
                code = status.name if isinstance(status, grpc.StatusCode) else "INTERNAL"
                raise
            finally:
                self._set_depth(estimator, -1)
                self._observe("Estimate", estimator, code, started)

        return estimate

    def _wrap_track(self, behaviour, parse):
        async def track(raw_iterator, context):
            if self.max_streams and self.streams >= self.max_streams:
                self._observe("Track", "-", REJECTED_CODE, None)
                if self.retry_pushback_ms:
                    pushback = self.retry_pushback_ms * self._jitter.uniform(0.5, 1.5)
                    context.set_trailing_metadata(((PUSHBACK_KEY, str(round(pushback))),))
                await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                                    f"server is at capacity ({self.max_streams} streams); retry with backoff")
            self.streams += 1  # counted before the first await, so that two new streams cannot both slip in
            if self.metrics:
                self.metrics.set_streams(self.streams)
            # The servicer answers each request of the stream once, in order: feed it only the admitted
            # frames and take its next answer for each; refused and unreadable frames are answered here.
            admitted: asyncio.Queue = asyncio.Queue()

            async def admitted_requests():
                while True:
                    yield await admitted.get()

            answers = behaviour(admitted_requests(), context).__aiter__()
            try:
                # Admitted: say so at once with the initial metadata, so that a client can wait for this answer
                # before it sends a 100 kB frame into a stream that might be refused.
                await context.send_initial_metadata(())
                async for raw in raw_iterator:
                    try:
                        request = parse(raw)
                    except DecodeError:
                        yield pb.EstimateResponse(status=pb.EstimateResponse.INVALID_INPUT, message=UNREADABLE)
                        continue
                    estimator = self.resolve(request.estimator)
                    if not self._admit(estimator):
                        self._observe("Track", estimator, REJECTED_CODE, None)
                        yield pb.EstimateResponse(frame_id=request.frame_id, capture_time_ns=request.capture_time_ns,
                                                  status=pb.EstimateResponse.UNAVAILABLE,
                                                  message=overload_message(estimator, self.max_queue))
                        continue
                    started = time.perf_counter()
                    admitted.put_nowait(request)
                    try:
                        response = await answers.__anext__()
                    except asyncio.CancelledError:  # the stream was cancelled with this frame in work (now ended)
                        self._observe("Track", estimator, _cancelled_code(context), started)
                        raise
                    finally:
                        self._set_depth(estimator, -1)
                    self._observe("Track", estimator, pb.EstimateResponse.Status.Name(response.status), started)
                    yield response
            except asyncio.CancelledError:
                if not self.stopping:
                    raise
                # gRPC cancels the streams still open at the end of a stop, wherever they wait: end quietly, the
                # process is leaving (raised, gRPC would print the CancelledError's traceback on stderr)
            finally:
                self.streams -= 1
                if self.metrics:
                    self.metrics.set_streams(self.streams)
                try:
                    await answers.aclose()  # the servicer waits at its last answer: end it there
                except asyncio.CancelledError:
                    if not self.stopping:
                        raise

        return track


UNREADABLE = "the request bytes are not a valid flextrack.v1 request message"


def _cancelled_code(context) -> str:
    """How a call that was cancelled under its handler is counted: its deadline passed, or the client left."""
    remaining = context.time_remaining()
    return "DEADLINE_EXCEEDED" if remaining is not None and remaining <= 0 else "CANCELLED"


async def _parse_or_abort(parse, raw, context):
    try:
        return parse(raw)
    except DecodeError:
        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, UNREADABLE)


def _wrap_parse_only(behaviour, parse):
    async def call(raw, context):
        return await behaviour(await _parse_or_abort(parse, raw, context), context)

    return call
