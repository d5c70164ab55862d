"""A gRPC client interceptor that puts the paper's network model between the device and the backend.

It wraps `Estimate` (unary) and `Track` (bidirectional stream) calls. For each request it draws
the uplink and downlink delays from `network_model.sample`, keyed by the request's frame id so
that the draw is a pure function of (seed, frame id, payload size).

- live (`live=True`): it sleeps the uplink delay before the request goes out and the downlink
  delay before a response is handed to the caller, so real time passes as on the modelled link;
- replay (`live=False`): it sleeps nothing and stamps the delays in `stamps` (frame id ->
  `LinkDelays`, taken with `pop_stamp`) and/or passes them to `on_delay`, for the virtual-time
  runner to apply on its own clock.

What it keeps per frame is bounded: an uplink delay waits for its response (a frame whose stream
broke never gets one) and a stamp for `pop_stamp`; each table keeps its `MAX_KEPT` newest entries,
so an hour of frames costs no more memory than a minute.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import grpc

from client_sdk import network_model
from client_sdk.network_model import LinkDelays, NetworkOptions

MAX_KEPT = 256  # frames a table remembers: far more than a device keeps in flight (one, in the PRM)


def _keep(table: dict[int, Any], key: int, value: Any, limit: int = MAX_KEPT) -> None:
    """table[key] = value, dropping the oldest entries past `limit` (dicts keep insertion order)."""
    table[key] = value
    while len(table) > limit:
        del table[next(iter(table))]


class LatencyInterceptor(grpc.UnaryUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    def __init__(self, options: NetworkOptions | None = None, *, live: bool = True,
                 on_delay: Callable[[int, LinkDelays], None] | None = None,
                 sleep: Callable[[float], None] = time.sleep):
        self.options = options or NetworkOptions()
        self.live = live
        self.on_delay = on_delay
        self._sleep = sleep
        self._lock = threading.Lock()
        self._uplinks: dict[int, int] = {}  # frame id -> uplink ns, until its response comes
        self.stamps: dict[int, LinkDelays] = {}  # replay only: frame id -> both legs

    def pop_stamp(self, frame_id: int) -> LinkDelays | None:
        with self._lock:
            return self.stamps.pop(int(frame_id), None)

    # -- the two legs --------------------------------------------------------------------------
    def _uplink(self, request) -> None:
        delays = network_model.sample(self.options, request.frame_id, request.ByteSize())
        with self._lock:
            _keep(self._uplinks, request.frame_id, delays.uplink_ns)
        if self.live:
            self._sleep(delays.uplink_ns * 1e-9)

    def _downlink(self, request_frame_id: int, response) -> None:
        delays = network_model.sample(self.options, request_frame_id, 0, response.ByteSize())
        with self._lock:
            up = self._uplinks.pop(request_frame_id, 0)
            both = LinkDelays(uplink_ns=up, downlink_ns=delays.downlink_ns)
            if not self.live:
                _keep(self.stamps, request_frame_id, both)
        if self.live:
            self._sleep(delays.downlink_ns * 1e-9)
        if self.on_delay is not None:
            self.on_delay(request_frame_id, both)

    # -- grpc hooks ----------------------------------------------------------------------------
    def intercept_unary_unary(self, continuation, client_call_details, request):
        self._uplink(request)
        outcome = continuation(client_call_details, request)
        if outcome.exception() is None:  # blocks until the answer is in
            self._downlink(request.frame_id, outcome.result())
        return outcome

    def intercept_stream_stream(self, continuation, client_call_details, request_iterator):
        sent: list[int] = []  # frame ids in flight, oldest first (responses come in order)
        sent_lock = threading.Lock()

        def delayed_requests() -> Iterator:
            for request in request_iterator:
                self._uplink(request)
                with sent_lock:
                    sent.append(request.frame_id)
                yield request

        call = continuation(client_call_details, delayed_requests())
        return _DelayedResponses(call, self, sent, sent_lock)


class _DelayedResponses:
    """The stream call, with each response held back by its downlink delay before delivery."""

    def __init__(self, call, interceptor: LatencyInterceptor, sent: list[int], sent_lock: threading.Lock):
        self._call = call
        self._interceptor = interceptor
        self._sent = sent
        self._sent_lock = sent_lock

    def __iter__(self):
        return self

    def __next__(self):
        response = next(self._call)
        with self._sent_lock:
            frame_id = self._sent.pop(0) if self._sent else response.frame_id
        self._interceptor._downlink(frame_id, response)
        return response

    def __getattr__(self, name):  # cancel(), code(), details(), is_active(), ...
        return getattr(self._call, name)
