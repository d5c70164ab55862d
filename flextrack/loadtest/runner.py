"""The load generator: N simulated devices, each a gRPC stream at its frame rate, on one grpc.aio loop.

Why grpc.aio and not locust: a device is one long-lived bidirectional `Track` stream with one
request in flight (the PRM sends a frame only when the previous answer is back). That is one
coroutine per device here, thousands of which fit on one event loop. Locust models users doing
request/response tasks (its gRPC support wraps unary calls on gevent), so a stream with pacing and
skipped frames would have to be rebuilt inside it anyway, through a second concurrency model.

Each client ticks at `fps`. At a tick it sends the frame if nothing is in flight; ticks that pass
while a request is out are counted as skipped frames, as a device would drop them. After a failed
call (a gRPC error: server gone, stream refused) it backs off exponentially with jitter (the SDK's own
`client_sdk.transport.Backoff` with its default options), or as long as a refusing server's
`grpc-retry-pushback-ms` asks, before the next attempt, as the SDK's TrackClient does. Every answer is one `Sample`: send time, latency and an outcome label, `OK`,
`status:<EstimateResponse.Status>` or `grpc:<StatusCode>` for a failed call or stream.

A run measures for `duration_s`, or, with `answers` set, until every client has that many answers
measured: an event, not a time window, so that a busy machine gives fewer answers a second, never
an empty run. `duration_s` then only bounds the run.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import grpc
import numpy as np

from client_sdk.transport import Backoff, TransportOptions, retry_pushback_s
from flextrack.loadtest.workload import Workload
from flextrack.v1 import pose_estimation_pb2 as pb

TRACK = "/flextrack.v1.PoseEstimation/Track"
ESTIMATE = "/flextrack.v1.PoseEstimation/Estimate"
MAX_MESSAGE_BYTES = 16 * 1024 * 1024
CONNECT_SETTLE_S = 0.5  # time for a channel to connect to every address of a multi-address target
PUSHBACK_MAX_S = TransportOptions.pushback_max_s


@dataclass(frozen=True)
class LoadSpec:
    targets: tuple[str, ...]
    clients: int
    fps: float = 30.0
    duration_s: float = 10.0  # measured seconds; with `answers`, the most a run may take
    warmup_s: float = 1.0  # samples sent before this are dropped (connection set-up)
    rpc: str = "track"  # "track" (bidi stream) or "estimate" (unary)
    channels: int = 1  # grpc channels the clients share round-robin; 0 = one per client
    deadline_s: float = 5.0  # per unary call; a stream read waiting longer counts as DEADLINE_EXCEEDED
    seed: int = 0
    answers: int = 0  # > 0: each client stops after this many measured answers (duration_s bounds the run)
    metadata: tuple[tuple[str, str], ...] = ()
    credentials: grpc.ChannelCredentials | None = None  # TLS (and token) credentials; None = plaintext
    server_name: str | None = None  # name to check in the server's certificate, if not the target's host
    # Wait for a new stream's initial metadata (flextrack's admission answer) before the first frame. An
    # asyncio client whose write races a refusal sees INTERNAL instead of RESOURCE_EXHAUSTED; but a server
    # that sends no early metadata (the echo servicer) would stall the first frame until its answer.
    await_admission: bool = False

    def __post_init__(self) -> None:
        if not self.targets:
            raise ValueError("give at least one target address")
        grpc_target(self.targets)  # refuses a list it cannot balance over
        if self.clients < 1 or self.fps <= 0 or self.duration_s <= 0 or self.warmup_s < 0 or self.answers < 0:
            raise ValueError("clients >= 1, fps > 0, duration_s > 0, warmup_s >= 0 and answers >= 0 are required")
        if self.rpc not in ("track", "estimate"):
            raise ValueError(f"rpc must be 'track' or 'estimate', not {self.rpc!r}")


@dataclass(frozen=True)
class Sample:
    client: int
    frame: int
    sent_s: float  # since the start of measurement (after warm-up)
    latency_ms: float
    outcome: str


@dataclass
class LoadResult:
    spec: LoadSpec
    samples: list[Sample] = field(default_factory=list)
    sent: int = 0  # requests sent after warm-up
    skipped: int = 0  # frame ticks after warm-up not sent because a request was still in flight
    measured_s: float = 0.0
    last_answer_at: float = 0.0  # perf_counter time of the last measured answer


def grpc_target(targets: tuple[str, ...] | list[str]) -> str:
    """One gRPC target for the addresses: as is for one; `ipv4:a:p,b:q` for several IPv4 literals."""
    targets = [t.strip() for t in targets if t.strip()]
    if len(targets) == 1:
        return targets[0]
    if not all(_is_ipv4_hostport(t) for t in targets):
        raise ValueError(f"several targets must be IPv4 host:port literals (got {targets}); for host names use one "
                         "dns:///NAME:PORT target that resolves to every replica")
    return "ipv4:" + ",".join(targets)


def _is_ipv4_hostport(addr: str) -> bool:
    host, _, port = addr.rpartition(":")
    parts = host.split(".")
    return port.isdigit() and len(parts) == 4 and all(p.isdigit() and int(p) < 256 for p in parts)


def channel_options(server_name: str | None = None) -> list[tuple[str, object]]:
    options = [("grpc.lb_policy_name", "round_robin"),  # spread streams over every address of the target
               ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
               ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES)]
    return options + ([("grpc.ssl_target_name_override", server_name)] if server_name else [])


def _outcome(response: pb.EstimateResponse) -> str:
    return "OK" if response.status == pb.EstimateResponse.OK else \
        "status:" + pb.EstimateResponse.Status.Name(response.status)


class _Clock:
    def __init__(self, spec: LoadSpec):
        self.t0 = time.perf_counter()
        self.measure_from = self.t0 + spec.warmup_s
        self.end = self.measure_from + spec.duration_s


async def _client(idx: int, spec: LoadSpec, workload: Workload, channel: grpc.aio.Channel, clock: _Clock,
                  offset_s: float, result: LoadResult) -> None:
    period = 1.0 / spec.fps
    next_tick = clock.t0 + offset_s
    frame = 0
    backoff = Backoff(TransportOptions(seed=spec.seed * 1_000_003 + idx))  # a device's, seeded per client
    call = None
    measured = 0
    deserialize = pb.EstimateResponse.FromString
    track = channel.stream_stream(TRACK, request_serializer=None, response_deserializer=deserialize)
    estimate = channel.unary_unary(ESTIMATE, request_serializer=None, response_deserializer=deserialize)
    try:
        while True:
            now = time.perf_counter()
            if now < next_tick:
                await asyncio.sleep(next_tick - now)
            if next_tick >= clock.end or (spec.answers and measured >= spec.answers):
                return
            request = workload.request(idx, frame)
            sent = time.perf_counter()
            pushback = 0.0
            try:
                if spec.rpc == "estimate":
                    outcome = _outcome(await estimate(request, timeout=spec.deadline_s, metadata=spec.metadata))
                else:
                    if call is None:
                        call = track(metadata=spec.metadata)
                        if spec.await_admission:
                            await asyncio.wait_for(call.initial_metadata(), spec.deadline_s)
                    response = grpc.aio.EOF
                    if not call.done():
                        await call.write(request)
                        response = await asyncio.wait_for(call.read(), spec.deadline_s)
                    if response is grpc.aio.EOF:  # refused, or ended by the server: count it, open a new one
                        pushback = retry_pushback_s(await call.trailing_metadata())
                        outcome, call = f"grpc:{(await call.code()).name}", None
                    else:
                        outcome = _outcome(response)
            except grpc.aio.AioRpcError as exc:
                # a write to a stream the server already ended fails with INTERNAL: the call's status says why
                code = (await call.code()) if call is not None and call.done() else exc.code()
                pushback = retry_pushback_s(exc.trailing_metadata())
                outcome, call = f"grpc:{code.name}", _cancel(call)
            except (TimeoutError, grpc.aio.UsageError):
                outcome, call = "grpc:DEADLINE_EXCEEDED", _cancel(call)
            done = time.perf_counter()
            frame += 1
            # A failed call backs off as a device's client does (exponential, jittered, or as long as the
            # server's pushback asks); frames meanwhile are tracked on the IMU, i.e. skipped here.
            if outcome.startswith("grpc:"):
                retry_at = done + max(backoff.next_s(), min(pushback, PUSHBACK_MAX_S))
            else:
                backoff.reset()
                retry_at = done
            ticks = max(1, int(np.ceil((retry_at - next_tick) / period)))  # the next tick after the answer
            next_tick += ticks * period
            if sent >= clock.measure_from:
                measured += 1
                result.last_answer_at = max(result.last_answer_at, done)
                result.sent += 1
                result.skipped += ticks - 1
                result.samples.append(Sample(idx, frame - 1, sent - clock.measure_from, (done - sent) * 1e3, outcome))
    finally:
        _cancel(call)


def _cancel(call) -> None:
    """Cancel a stream (if any); returns None so that `call = _cancel(call)` forgets it."""
    if call is not None:
        call.cancel()


async def run_load(spec: LoadSpec, workload: Workload) -> LoadResult:
    """Run the clients against the target for warm-up + duration (or until each has `answers` measured
    answers) and collect every answer."""
    target = grpc_target(spec.targets)
    n_channels = spec.clients if spec.channels == 0 else max(1, min(spec.channels, spec.clients))
    options = channel_options(spec.server_name)
    make = (lambda: grpc.aio.secure_channel(target, spec.credentials, options=options)) \
        if spec.credentials else (lambda: grpc.aio.insecure_channel(target, options=options))
    channels = [make() for _ in range(n_channels)]
    result = LoadResult(spec)
    rng = np.random.default_rng(spec.seed)
    try:
        if len(spec.targets) > 1:
            # round_robin deals streams out over the addresses whose connection is up when the stream opens; a
            # channel connects to all at once, but a stream opened in the first milliseconds sees only the first.
            await asyncio.gather(*(asyncio.wait_for(ch.channel_ready(), spec.deadline_s) for ch in channels))
            await asyncio.sleep(CONNECT_SETTLE_S)
        clock = _Clock(spec)
        offsets = rng.uniform(0.0, 1.0 / spec.fps, spec.clients)  # devices are not in step
        await asyncio.gather(*(_client(i, spec, workload, channels[i % n_channels], clock, float(offsets[i]), result)
                               for i in range(spec.clients)))
        if not spec.answers:
            result.measured_s = spec.duration_s
        else:  # from the start of measurement to the last answer, or to the bound when none came
            end = result.last_answer_at if result.samples else time.perf_counter()
            result.measured_s = max(end - clock.measure_from, 1e-9)
    finally:
        await asyncio.gather(*(ch.close() for ch in channels))
    return result


def run(spec: LoadSpec, workload: Workload) -> LoadResult:
    return asyncio.run(run_load(spec, workload))
