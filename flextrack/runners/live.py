"""Run the tracker in real time: the sequence's IMU samples and frames are fed at their own pace
(scaled by `speed`), requests go out over a `TrackClient` whose `LatencyInterceptor` sleeps the
modelled network delays, and every frontend call is stretched by the device slowdown.

This is the shell a device would have: the same tracker core as the replay, fed by the clock. Its memory
levels off however long it runs: the filter keeps no error dynamics unless asked, and the record keeps its last
`keep_rows` rows in memory, the older ones on disk.
Responses arrive on the transport's thread and are applied by the main loop between events, so
the core is only ever touched by one thread. Unlike the replay, two live runs differ (real
scheduling and real delays); the errors they report are of the same size.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from client_sdk import TrackerOptions
from client_sdk.interceptor import LatencyInterceptor
from client_sdk.network_model import NetworkOptions
from client_sdk.slowdown import PIXEL2_FACTOR, Slowdown
from client_sdk.transport import TrackClient, TransportOptions
from flextrack.formats.sequence import Sequence
from flextrack.runners.exchange import apply_answer, finish, frame_latency_ns, frame_request, tracker_for
from flextrack.runners.payload import stand_in_jpeg
from flextrack.runners.results import RowStore, TrackRecord
from flextrack.v1 import pose_estimation_pb2 as pb


@dataclass(frozen=True)
class LiveOptions:
    network: NetworkOptions = field(default_factory=NetworkOptions)
    slowdown: float = PIXEL2_FACTOR
    estimator: str = "gt"
    speed: float = 1.0  # 2.0 plays the sequence twice as fast (network delays are not scaled)
    transport: TransportOptions = field(default_factory=TransportOptions)
    connect_timeout_s: float = 10.0
    session_id: str = "live"
    # What grows with the frames is asked for, never implied: the filter's error dynamics (the model NEES
    # interval; without them the summary takes the interval from the NEES series' autocorrelation) and how
    # many of the record's rows stay in memory (the older ones go to a temporary file).
    record_error_dynamics: bool = False
    keep_rows: int = 1024


@dataclass
class Progress:
    t_s: float  # sequence time reached
    total_s: float
    record: TrackRecord
    status: str
    connected: bool


def _timeline(seq: Sequence) -> list[tuple[int, int, int]]:
    """(t_ns, kind, index) of every IMU sample (kind 0) and frame (kind 1), in the order they reach the tracker: a
    frame the sequence's frame latency after its capture time (`exchange.frame_latency_ns`)."""
    latency = frame_latency_ns(seq)
    imu = [(int(t), 0, i) for i, t in enumerate(seq.imu.t_ns)]
    frames = [(int(t) + latency, 1, i) for i, t in enumerate(seq.frame_times_ns)]
    return sorted(imu + frames)


def run_live(seq: Sequence, address: str, vertices_O: np.ndarray, tracker_options: TrackerOptions | None = None,
             options: LiveOptions = LiveOptions(), progress: Callable[[Progress], None] | None = None,
             progress_every_s: float = 0.25, frame_jpeg: Callable[[int], bytes] | None = None) -> TrackRecord:
    """Track `seq` in real time against the server at `address`; raises ConnectionError if it never answers.
    `frame_jpeg(frame_id)` gives the image a request carries (default: the 90 kB stand-in)."""
    if options.speed <= 0:
        raise ValueError(f"speed must be > 0, got {options.speed}")
    tracker = tracker_for(seq, vertices_O, tracker_options, options.record_error_dynamics)
    slowdown = Slowdown(options.slowdown)
    record = TrackRecord(seq.camera, vertices_O, RowStore(options.keep_rows))
    image = stand_in_jpeg(seq.camera.width, seq.camera.height)
    inbox: queue.Queue = queue.Queue()
    pending: dict[int, object] = {}  # wire frame id -> the tracker's RefinementRequest
    interceptor = LatencyInterceptor(options.network, live=True)
    client = TrackClient(address, on_response=lambda r: inbox.put((r, "")),
                         on_failure=lambda frame_id, why: inbox.put((frame_id, why)),
                         interceptors=[interceptor], options=options.transport)

    def apply(message) -> None:
        item, why = message
        frame_id = item.frame_id if isinstance(item, pb.EstimateResponse) else item
        request = pending.pop(frame_id, None)
        if request is None:
            return
        with slowdown.stretch():
            if why:
                record.failures += 1
                tracker.on_backend_failure(request.request_id)
            else:
                apply_answer(tracker, request.request_id, item, record)

    timeline = _timeline(seq)
    t_first, t_last = timeline[0][0], timeline[-1][0]
    status, next_progress = "INITIALIZING", 0.0
    with client:
        if not client.wait_connected(options.connect_timeout_s):
            raise ConnectionError(f"no backend answered at {address} within {options.connect_timeout_s} s")
        wall0 = time.perf_counter()
        for t_ns, kind, i in timeline:
            due = wall0 + (t_ns - t_first) * 1e-9 / options.speed
            while True:
                try:
                    message = inbox.get(timeout=max(0.0, due - time.perf_counter()))
                except queue.Empty:
                    break
                apply(message)
            if kind == 0:
                with slowdown.stretch():
                    tracker.add_imu(t_ns, seq.imu.gyro[i], seq.imu.accel[i])
                continue
            frame_id = int(seq.frame_ids[i])
            t_ns = int(seq.frame_times_ns[i])  # stamped with its capture time
            with slowdown.stretch():
                result = tracker.add_frame(t_ns)
                state = tracker.state_bytes() if result.request is not None else b""
            status = result.status.name
            if result.request is not None:
                request = frame_request(seq, tracker, frame_id, result.request.frame_t_ns,
                                        image if frame_jpeg is None else frame_jpeg(frame_id),  # camera: not stretched
                                        session_id=options.session_id, estimator=options.estimator,
                                        client_state=state)
            record.add(frame_id, t_ns, status, result.T_CO, seq.gt_T_CO.get(frame_id), result.covariance)
            if result.request is not None:
                record.requests += 1
                pending[frame_id] = result.request
                if not client.submit(request):
                    pending.pop(frame_id)
                    record.failures += 1
                    tracker.on_backend_failure(result.request.request_id)
            now = time.perf_counter()
            if progress is not None and now >= next_progress:
                next_progress = now + progress_every_s
                progress(Progress((t_ns - t_first) * 1e-9, (t_last - t_first) * 1e-9, record, status,
                                  client.connected))
        if progress is not None:
            progress(Progress((t_last - t_first) * 1e-9, (t_last - t_first) * 1e-9, record, status, client.connected))
    return finish(tracker, record)
